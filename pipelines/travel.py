"""What could set VQF's two time constants on a sensor it never saw (``togglecf.run.travel``): trial
statistics of the sensor's own signals, a reference-free self-tuning, and the ceilings, each choosing a
pair per trial from its first half or from other datasets and scored on its second half.

    python pipelines/travel.py                        # BROAD and every dataset beside it
    python pipelines/travel.py --data ../shared/data/broad --data ../shared/data/tyrex_nexus5
    python pipelines/travel.py --quick                # a 2 x 2 grid (tests, a first look)

Writes OUT/travel.md (``pipelines/regenerate_docs.py --travel OUT`` copies it into docs/results/) and
OUT/travel.json (every trial's grid, statistics and scores). About 5 min for the three developer datasets
on 2 cores.
"""
from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path

from togglecf.core.log import setup_logging
from togglecf.data.broad import DataNotFoundError, resolve_data_dir
from togglecf.run.lodo import dataset_dirs
from togglecf.run.travel import run_travel, travel_settings

log = logging.getLogger("togglecf.travel")


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0], epilog=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--data", action="append", metavar="DIR",
                   help="a dataset directory in BROAD's layout (repeatable; default: BROAD and those beside it)")
    p.add_argument("--out", default="reports/travel", metavar="DIR")
    p.add_argument("--quick", action="store_true", help="a 2 x 2 grid around VQF's defaults")
    p.add_argument("--jobs", type=int, default=0, help="worker processes (0: all cores)")
    args = p.parse_args(argv)
    try:
        dirs = [Path(d) for d in args.data] if args.data else dataset_dirs(resolve_data_dir(None))
    except DataNotFoundError as exc:
        p.error(f"no dataset given and BROAD not found ({str(exc).splitlines()[0]}); pass --data DIR")
    missing = [str(d) for d in dirs if not (d / "trials.json").is_file()]
    if missing:
        p.error(f"not a dataset in BROAD's layout (no trials.json): {', '.join(missing)}")
    if len(dirs) < 2:
        p.error("leaving a dataset out needs at least two datasets (pass --data twice)")
    command = "python pipelines/travel.py" + "".join(f" --data {d}" for d in args.data or ()) + (
        " --quick" if args.quick else "")
    run_travel(dirs, args.out, travel_settings(args.quick, jobs=args.jobs), command)
    print((Path(args.out) / "travel.md").read_text())
    return 0


if __name__ == "__main__":
    setup_logging()
    sys.exit(main())
