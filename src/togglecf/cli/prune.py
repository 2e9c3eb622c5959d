"""``togglecf prune``: the pruning sweep (``togglecf.run.prune``) from the command line, and the
sweep options that ``togglecf export --max-bytes`` shares."""
from __future__ import annotations

import logging
import shutil

from togglecf.cli.common import add_backend_args, backend_settings
from togglecf.embedded.toolchain import RISCV_GCC
from togglecf.learn.models import load_bundle
from togglecf.parallel.backend import InlineBackend, make_backend
from togglecf.run.config import load_config
from togglecf.run.prune import (
    SIZE_KEYS,
    choose_point,
    default_points,
    format_front,
    pruning_sweep,
    size_key,
    write_sweep_report,
)

__all__ = ["add_prune_parser", "add_sweep_arguments", "sweep_from_args"]

log = logging.getLogger(__name__)


def _ints(text: str) -> tuple:
    try:
        vals = tuple(int(v) for v in text.split(",") if v.strip())
    except ValueError:
        raise ValueError(f"expected comma-separated integers, got {text!r}") from None
    if not vals or min(vals) < 0:
        raise ValueError(f"expected non-negative integers, got {text!r}")
    return vals


def add_sweep_arguments(sp):
    """The grid and protocol options shared by ``togglecf prune`` and ``togglecf export --max-bytes``
    (both also have ``--models``, ``--data`` and ``--no-riscv``)."""
    sp.add_argument("--trees", default="10,20,30", metavar="LIST", help="trees per booster (default: 10,20,30)")
    sp.add_argument("--depths", default="3,4", metavar="LIST", help="tree depths (default: 3,4)")
    sp.add_argument("--features", default="0,24,12", metavar="LIST",
                    help="number of most important features the trees may use, 0 = all (default: 0,24,12)")
    sp.add_argument("--folds", type=int, default=5, help="held-out folds by whole trial (default: 5, as the study)")
    sp.add_argument("--inner-folds", type=int, default=3, help="CV folds inside each training set, whose "
                    "out-of-fold predictions the gains are learned on (default: 3, as the study)")
    add_backend_args(sp)  # dask: every (point, fold) a task; the sweep directory must be shared with the workers


def sweep_from_args(args, sweep_dir, log=log.info) -> list:
    """The sweep of ``add_sweep_arguments``' options. ``--backend local`` (default) runs the
    folds one after another here (each already uses the cores: XGBoost threads, the gain
    search's process pool); ``--backend dask`` runs every (point, fold) on the cluster."""
    cfg = load_config(load_bundle(args.models).metadata["config"])
    pts = default_points(cfg, _ints(args.trees), _ints(args.depths), _ints(args.features))
    s = backend_settings(args, cfg["run"])
    backend = make_backend("dask", s["scheduler"], retries=s["retries"]) if s["backend"] == "dask" else InlineBackend()
    with backend:
        return pruning_sweep(args.models, sweep_dir, pts, folds=args.folds, inner_folds=args.inner_folds,
                             data_dir=args.data, riscv=not args.no_riscv, log=log, backend=backend)


def add_prune_parser(subparsers):
    sp = subparsers.add_parser("prune", help="pruning sweep: model size against the toggling filter's held-out "
                               "BROAD error; Pareto front as CSV and plot")
    sp.add_argument("--models", required=True, metavar="DIR", help="the `togglecf train` model directory to prune "
                    "(its config, training trials and gain search are kept; only model sizes change)")
    sp.add_argument("--out", required=True, metavar="DIR", help="sweep directory (resumable: finished points "
                    "are kept in DIR/sweep_rows.jsonl)")
    sp.add_argument("--max-bytes", type=int, metavar="N", help="mark this budget and name the best point within it")
    sp.add_argument("--format", choices=tuple(SIZE_KEYS), default="array",
                    help="code format whose RISC-V object size is the size axis (default: array)")
    add_sweep_arguments(sp)
    sp.add_argument("--data", metavar="DIR", action="append", default=None,
                    help="data directory, repeatable (default: the directories the models were trained on when "
                    "they were several, else the default location)")
    sp.add_argument("--no-riscv", action="store_true", help="host sizes only")
    sp.set_defaults(func=cmd_prune)
    return sp


def cmd_prune(args) -> int:
    rows = sweep_from_args(args, args.out)
    key = size_key(args.format, not args.no_riscv and shutil.which(RISCV_GCC) is not None)
    paths = write_sweep_report(rows, args.out, key, args.max_bytes)
    print(format_front(rows, key))
    print(f"wrote {paths['sweep']}, {paths['pareto']}, {paths['plot']}")
    if args.max_bytes:
        best = choose_point(rows, args.max_bytes, key)
        ref = next(r for r in rows if r["reference"])
        print(f"best within {args.max_bytes} bytes: {best['key']} ({best[key]} bytes, mean total "
              f"{best['mean_total']:.3f}°, {best['mean_total'] - ref['mean_total']:+.3f}° vs unpruned)")
    return 0
