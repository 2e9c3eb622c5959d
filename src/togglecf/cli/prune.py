"""``togglecf prune``: the pruning sweep (``togglecf.run.prune``) from the command line, and the
sweep that ``togglecf export --max-bytes`` shares. The parsers are ``cli.parsers.add_prune_parser`` and
``add_sweep_arguments``; this module is imported when a command runs (the ``export`` and ``plot`` extras)."""
from __future__ import annotations

import logging
import shutil

from togglecf.cli.common import backend_settings
from togglecf.cli.parsers import add_prune_parser, add_sweep_arguments
from togglecf.embedded.toolchain import RISCV_GCC
from togglecf.learn.models import load_bundle
from togglecf.parallel.backend import InlineBackend, make_backend
from togglecf.run.config import load_config
from togglecf.run.prune import (
    choose_point,
    default_points,
    format_front,
    pruning_sweep,
    size_key,
    write_sweep_report,
)

__all__ = ["add_prune_parser", "add_sweep_arguments", "sweep_from_args", "cmd_prune"]

log = logging.getLogger(__name__)


def _ints(text: str) -> tuple:
    try:
        vals = tuple(int(v) for v in text.split(",") if v.strip())
    except ValueError:
        raise ValueError(f"expected comma-separated integers, got {text!r}") from None
    if not vals or min(vals) < 0:
        raise ValueError(f"expected non-negative integers, got {text!r}")
    return vals


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
