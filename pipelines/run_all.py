"""The full held-out study: train with CV folds, evaluate all filters, write the report.

    python pipelines/run_all.py [--data DIR [--data DIR2 ...]] [--out reports/study]
                                [--config TOML (default togglecf/configs/study.toml)]
                                [--trials 01,02,...] [--folds K] [--fold-seed N] [--ablations LIST]
                                [--backend local|dask [--scheduler tcp://HOST:8786]] [--jobs N]

The folds run as tasks on the backend: a local process pool (default, ``--jobs`` processes, default
the config's ``[study] jobs``, 0 = all cores) or a Dask cluster (its workers must read the data
directories and write ``--out``: a shared filesystem).

Writes reports/study/{summary.md, per_trial.csv, per_trial_total.csv, per_group.csv, results.json,
plots/*.png, folds/fold<k>/models/} (see togglecf.run.study and togglecf.report.study_report).
"""
import argparse
import os
import sys
from dataclasses import replace

from togglecf.core.config import BACKENDS
from togglecf.core.log import setup_logging
from togglecf.parallel.backend import BackendError, LocalBackend, make_backend
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
    p.add_argument("--backend", choices=BACKENDS, default="local", help="where the folds run (default: local)")
    p.add_argument("--scheduler", metavar="ADDR", help="Dask scheduler address (with --backend dask)")
    p.add_argument("--jobs", type=int, help="local worker processes (default: [study] jobs of the config)")
    args = p.parse_args(argv)
    cfg = load_study_config(args.config)
    if args.folds:
        cfg = replace(cfg, folds=args.folds)
    if args.fold_seed is not None:
        cfg = replace(cfg, fold_seed=args.fold_seed)
    if args.ablations is not None:
        cfg = replace(cfg, ablations=tuple(a for a in args.ablations.split(",") if a))
    if args.jobs is not None:
        cfg = replace(cfg, jobs=args.jobs)
    try:
        backend = (LocalBackend(min(cfg.jobs or os.cpu_count() or 1, cfg.folds), start_method="forkserver")
                   if args.backend == "local" else make_backend(args.backend, args.scheduler))
    except BackendError as exc:
        p.error(str(exc))
    with backend:
        run_study(cfg, data_dir=args.data, out_dir=args.out, trials=args.trials, backend=backend)
    return 0


if __name__ == "__main__":
    setup_logging()
    sys.exit(main())
