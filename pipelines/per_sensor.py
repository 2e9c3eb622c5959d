"""Your sensor, measured: the learned VQF re-learned on each dataset's own recordings, against VQF.

    python pipelines/per_sensor.py                      # every dataset beside BROAD -> reports/per_sensor/
    python pipelines/per_sensor.py --data ../shared/data/tyrex_nexus5 --sizes 2,4,8,all --scratch-sizes all
    python pipelines/per_sensor.py --quick              # 2 folds, 2 and all recordings, no scratch: the plumbing
    python pipelines/per_sensor.py --half               # the kept-back check's split -> per_sensor_half.md
    python pipelines/per_sensor.py --half --config my.toml   # another training config (e.g. its [gains.vqf] grids)
    python pipelines/per_sensor.py --half --field-change     # the scratch training searches σ_f too

For each dataset alone (``togglecf.run.per_sensor``): folds by whole trial within it; on 2, 4, 8 and
all of a fold's training recordings, VQF tuned (τ_acc × τ_mag TAGP), the learned VQF re-learned
from a model that never saw the dataset (``togglecf train --from-pretrained``) and trained from
scratch; every held-out trial scored beside VQF's defaults. The base of the re-learning for a
dataset is the pretrained recipe trained on the *other* datasets: leave-one-dataset-out's models
(``--base-from``, default ``build/lodo``, what ``make run`` writes as ``without_<name>/models``), or,
when there are none, trained here first into ``<work>/base/without_<name>`` (minutes).

Writes ``<out>/per_sensor.md`` (its first line names this command and the code) and
``per_sensor.json`` (every held-out trial's errors); the models go to ``--work`` (``build/per_sensor``).
``--half``: the kept-back check's own split (2 folds, each half re-learned and trained on, the other half
scored; ``run.per_sensor.HALF``) -> ``per_sensor_half.md`` / ``.json``, models in ``<work>_half``.
The re-learning searches σ_f, the scale of the learned VQF's back-off on the field's change, as ``togglecf train
--from-pretrained`` does (``[gains.relearn]``); ``--field-change``: the scratch training searches it too
(``run.per_sensor.with_field_change``) -> ``<name>_field_change.md`` / ``.json``,
models in ``<work>_field_change``. ``python pipelines/main.py --full`` runs the learning curve and the half split,
each with and without ``--field-change``.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

from togglecf.core.io import atomic_write_json, atomic_write_text
from togglecf.core.log import setup_logging
from togglecf.data.broad import DataNotFoundError, resolve_data_dir
from togglecf.run.lodo import dataset_dirs
from togglecf.run.per_sensor import (HALF, PerSensorConfig, base_models, per_sensor, per_sensor_json, per_sensor_table,
                                     with_field_change)

OUT_DIR = Path("reports/per_sensor")
WORK_DIR = Path("build/per_sensor")
BASE_FROM = Path("build/lodo")
QUICK = PerSensorConfig(folds=2, sizes=(2, 0), scratch_sizes=())


def _sizes(text: str) -> tuple:
    out = []
    for item in (s.strip() for s in text.split(",") if s.strip()):
        if item == "all":
            out.append(0)
        elif item.isdigit() and int(item) >= 2:
            out.append(int(item))
        else:
            raise argparse.ArgumentTypeError(f"{item!r}: a size is a whole number of recordings >= 2, or 'all'")
    return tuple(out)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0], epilog=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--data", action="append", metavar="DIR",
                   help="a dataset in BROAD's layout (repeatable; default: BROAD and every dataset beside it)")
    p.add_argument("--base-from", type=Path, default=BASE_FROM, metavar="DIR",
                   help="leave-one-dataset-out's output with without_<name>/models (default: %(default)s)")
    p.add_argument("--folds", type=int, default=PerSensorConfig.folds)
    p.add_argument("--sizes", type=_sizes, default=PerSensorConfig.sizes, help="e.g. 2,4,8,all")
    p.add_argument("--scratch-sizes", type=_sizes, default=PerSensorConfig.scratch_sizes,
                   help="sizes at which the learned VQF is also trained from scratch (e.g. all; '' none)")
    p.add_argument("--seed", type=int, default=0, help="fold assignment and training subsets (0: round-robin)")
    p.add_argument("--quick", action="store_true", help="2 folds, 2 and all recordings, no scratch training")
    p.add_argument("--half", action="store_true", help="the kept-back check's split: 2 folds, all of each half "
                   "(re-learned and from scratch) -> per_sensor_half.md")
    p.add_argument("--out", type=Path, default=OUT_DIR, metavar="DIR", help="the tables (default: %(default)s)")
    p.add_argument("--config", type=Path, default=None, metavar="TOML",
                   help="the training config of the re-learning and the scratch training (default: the package's)")
    p.add_argument("--field-change", action="store_true", help="the scratch training searches the field-change "
                   "back-off's scale too, as the re-learning does -> <name>_field_change.md")
    p.add_argument("--work", type=Path, default=WORK_DIR, metavar="DIR",
                   help="the re-learned and trained models, the bases trained here (default: %(default)s)")
    args = p.parse_args(argv)
    try:
        dirs = [Path(d) for d in args.data] if args.data else dataset_dirs(resolve_data_dir(None))
    except DataNotFoundError as exc:
        p.error(str(exc))
    if args.config is not None and not args.config.is_file():
        p.error(f"--config {args.config}: no such file")
    missing = [str(d) for d in dirs if not (d / "trials.json").is_file()]
    if missing:
        p.error(f"not a dataset in BROAD's layout (no trials.json): {', '.join(missing)}")
    if args.quick and args.half:
        p.error("--quick and --half: one of them")
    settings = QUICK if args.quick else HALF if args.half else PerSensorConfig(args.folds, args.sizes,
                                                                               args.scratch_sizes, args.seed)
    suffix = ("_half" if args.half else "") + ("_field_change" if args.field_change else "")
    name = "per_sensor" + suffix
    work = args.work.with_name(args.work.name + suffix)
    command = "python pipelines/per_sensor.py" + (" " + " ".join(argv if argv is not None else sys.argv[1:])
                                                  if (argv if argv is not None else sys.argv[1:]) else "")
    config = None if args.config is None else str(args.config)
    if args.field_change:
        config = with_field_change(config)
    results = per_sensor(dirs, work, base_models(dirs, args.base_from, work), settings, config=config)
    text = per_sensor_table(results, dirs, command)
    atomic_write_text(args.out / f"{name}.md", text)
    atomic_write_json(args.out / f"{name}.json", per_sensor_json(results))
    print(text)
    return 0


if __name__ == "__main__":
    setup_logging()
    sys.exit(main())
