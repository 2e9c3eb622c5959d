"""The full held-out study: train with CV folds, evaluate all filters, write the report.

    python pipelines/run_all.py [--data DIR [--data DIR2 ...]] [--out reports/study]
                                [--config TOML (default togglecf/configs/study.toml)]
                                [--trials 01,02,...] [--folds K] [--fold-seed N] [--ablations LIST]

Writes reports/study/{summary.md, per_trial.csv, per_trial_total.csv, per_group.csv, results.json,
plots/*.png, folds/fold<k>/models/} (see togglecf.run.study and togglecf.report.study_report).
"""
import argparse
import sys
from dataclasses import replace

from togglecf.core.log import setup_logging
from togglecf.run.study import DEFAULT_STUDY_CONFIG, load_study_config, run_study


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--data", metavar="DIR", action="append", default=None,
                   help="data directory, repeatable (names become <dir name>/<trial>); default: [run] data of "
                   "the study's train_config, else the default BROAD location")
    p.add_argument("--out", default="reports/study", metavar="DIR")
    p.add_argument("--config", default=str(DEFAULT_STUDY_CONFIG), metavar="TOML")
    p.add_argument("--trials", metavar="LIST")
    p.add_argument("--folds", type=int)
    p.add_argument("--fold-seed", type=int, help="another fold assignment (0: the standard one)")
    p.add_argument("--ablations", help="comma-separated subset of the config's ablations ('' for none)")
    args = p.parse_args(argv)
    cfg = load_study_config(args.config)
    if args.folds:
        cfg = replace(cfg, folds=args.folds)
    if args.fold_seed is not None:
        cfg = replace(cfg, fold_seed=args.fold_seed)
    if args.ablations is not None:
        cfg = replace(cfg, ablations=tuple(a for a in args.ablations.split(",") if a))
    run_study(cfg, data_dir=args.data, out_dir=args.out, trials=args.trials)
    return 0


if __name__ == "__main__":
    setup_logging()
    sys.exit(main())
