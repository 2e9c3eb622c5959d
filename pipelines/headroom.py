"""The headroom over VQF, per dataset and group: VQF at its defaults, its two time constants tuned
(held out), oracles of those two, per-state time constants driven by the true motion labels, the
heading back-off driven by the true field disturbance and by the field's change (at VQF's defaults and
at the tuned pair), and VQF's offline estimate (``togglecf.run.headroom``).

    python pipelines/headroom.py                       # BROAD and every dataset beside it
    python pipelines/headroom.py --data ../shared/data/broad --data ../shared/data/tyrex_nexus5
    python pipelines/headroom.py --quick --trials 02,07,24 --data tests/data/broad_mini

Writes OUT/headroom.md (the table; ``pipelines/regenerate_docs.py --headroom OUT`` copies it into
docs/results/) and OUT/headroom.json (every trial's numbers). The core's grid results are kept in
build/cache/ (keyed on the package's source and each trial file, shared with ``pipelines/main.py``).
``--quick``: a 2 x 2 grid and a small per-state search (tests, a first look; not the documented table).
"""
from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path

from togglecf import source_digest
from togglecf.core.log import setup_logging
from togglecf.data.broad import DataNotFoundError, resolve_data_dir
from togglecf.run.headroom import headroom_settings, run_headroom
from togglecf.run.lodo import dataset_dirs
from togglecf.run.sweep import ResultStore

CACHE_DIR = Path("build/cache")
log = logging.getLogger("togglecf.headroom")


def default_dirs() -> list[Path]:
    """BROAD (``resolve_data_dir``) and every directory in BROAD's layout beside it."""
    return dataset_dirs(resolve_data_dir(None))


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0], epilog=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--data", action="append", metavar="DIR",
                   help="a dataset directory in BROAD's layout (repeatable; default: BROAD and those beside it)")
    p.add_argument("--out", default="reports/headroom", metavar="DIR")
    p.add_argument("--quick", action="store_true", help="a 2 x 2 grid and a small per-state search")
    p.add_argument("--trials", default=None, help="comma-separated trial names or prefixes (default: all)")
    p.add_argument("--jobs", type=int, default=0, help="worker processes (0: all cores)")
    p.add_argument("--no-cache", action="store_true", help="compute every grid point anew (no build/cache)")
    args = p.parse_args(argv)
    try:
        dirs = [Path(d) for d in args.data] if args.data else default_dirs()
    except DataNotFoundError as exc:
        p.error(f"no dataset given and BROAD not found ({str(exc).splitlines()[0]}); pass --data DIR")
    missing = [str(d) for d in dirs if not (d / "trials.json").is_file()]
    if missing:
        p.error(f"not a dataset in BROAD's layout (no trials.json): {', '.join(missing)}")
    command = "python pipelines/headroom.py" + "".join(f" --data {d}" for d in args.data or ()) + (
        " --quick" if args.quick else "") + (f" --trials {args.trials}" if args.trials else "")
    settings = headroom_settings(args.quick, jobs=args.jobs)
    log.info(f"headroom on {', '.join(d.name for d in dirs)} ({'quick' if args.quick else 'full grid'})")
    if args.no_cache:
        results = run_headroom(dirs, args.out, settings, command, args.trials)
    else:
        with ResultStore(CACHE_DIR / f"classic-{source_digest()[:16]}.jsonl") as store:
            results = run_headroom(dirs, args.out, settings, command, args.trials, store)
    print((Path(args.out) / "headroom.md").read_text())
    return 0 if results else 1


if __name__ == "__main__":
    setup_logging()
    sys.exit(main())
