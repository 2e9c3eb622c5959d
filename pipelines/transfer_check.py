"""Does a trained filter travel? Score trained filters on data they were not trained on.

    python pipelines/transfer_check.py --models DIR --data OTHER_DIR --out docs/results/transfer_phone.md
    python pipelines/transfer_check.py --study reports/study --data DECIMATED_DIR --out docs/results/transfer_rate.md

* ``--models``: a model directory (``togglecf train``) scored on every trial of ``--data`` (another
  sensor, rate or motion: e.g. ``../shared/data/tyrex_nexus5``, trained on BROAD only).
* ``--study``: each fold's models of a held-out study scored on *its own test trials* read from
  ``--data`` (e.g. the same BROAD trials decimated 3x by ``pipelines/decimate.py``): held out, at
  another rate.

The protocol itself is ``togglecf.run.transfer`` (``make run`` runs it after the study). Beside the
trained filters (``toggling``, ``vqf_toggling``) the classic ones run at their defaults (``vqf_core`` =
VQF's defaults, ``madgwick``, ``cf``, ``ekf``). Writes a Markdown table (mean total RMSE [deg] over all
trials and per group of the data's ``trials.json``, and the trained filters' fallback share) whose first
line names the command and the run.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

from togglecf.core.log import setup_logging
from togglecf.data import DatasetIndex
from togglecf.run.transfer import models_transfer, study_transfer, transfer_table


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0], epilog=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--models", metavar="DIR")
    src.add_argument("--study", metavar="DIR")
    p.add_argument("--data", required=True, metavar="DIR")
    p.add_argument("--groups", default="undisturbed,mag_disturbed,disturbed", help="groups to list (if present)")
    p.add_argument("--out", metavar="FILE.md")
    args = p.parse_args(argv)
    index = DatasetIndex.from_dir(args.data)
    if args.models:
        per = models_transfer(args.models, index)
        what = f"models `{args.models}` on all {len(next(iter(per.values())))} trials of `{args.data}`"
    else:
        per = study_transfer(args.study, index)
        what = (f"each fold's models of the study `{args.study}` on its own test trials "
                f"({len(next(iter(per.values())))}) read from `{args.data}`")
    command = "python pipelines/transfer_check.py " + " ".join(argv if argv is not None else sys.argv[1:])
    text = transfer_table(per, index, what, command, groups=tuple(args.groups.split(",")))
    print(text)
    if args.out:
        Path(args.out).write_text(text)
    return 0


if __name__ == "__main__":
    setup_logging()
    sys.exit(main())
