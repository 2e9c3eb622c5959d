"""What every ``pipelines/bench_*.py`` shares: the ``--quick``/``--out``/``--data`` options, where the
mini data is, timing against VQF in the same run, and writing the result table (Markdown + CSV).

Not a benchmark itself. Each benchmark's ``main(argv)`` returns a dict with ``rows`` (the table),
``ratios`` (name -> time ÷ VQF's, measured in the same run on the same samples) and ``paths``
(the written files, empty in quick mode without ``--out``).
"""
from __future__ import annotations

import importlib.util

import os
import platform
import sys
import time
from pathlib import Path

import numpy as np

from togglecf import __version__
from togglecf.report.tables import markdown_table, write_table

REPO = Path(__file__).resolve().parents[1]
#: where the mini data's makers live: 14-s cuts of three real BROAD trials (``broad_mini``, made from
#: BROAD on first use) or, without BROAD, three synthetic trials (``synthetic_mini``); ``mini_data.py``
#: chooses, as for the test suite (``TOGGLECF_MINI``)
MINI_DATA_DIR = REPO / "tests" / "data"
#: where the full runs write their tables (the docs include ``<name>.md``)
BENCH_DIR = REPO / "reports" / "bench"


def add_common_args(p, name: str):
    p.add_argument("--quick", action="store_true",
                   help="seconds, on the mini data in tests/data (the real cuts broad_mini, or synthetic_mini "
                   "without BROAD; the test suite runs this); "
                   "writes a table only with --out")
    p.add_argument("--data", metavar="DIR", default=None,
                   help="BROAD directory (default: as `togglecf evaluate`; --quick: the mini data)")
    p.add_argument("--out", metavar="PATH", default=None,
                   help=f"table file: PATH.md and PATH.csv (default: reports/bench/{name}.md/.csv for a full run)")


def data_dir(args):
    """``--data``, else the mini directory in quick mode (the real cuts, or the synthetic trials without
    BROAD: ``tests/data/mini_data.py``), else ``None`` (resolved as the CLI does)."""
    if args.data:
        return args.data
    if not args.quick:
        return None
    spec = importlib.util.spec_from_file_location("mini_data", MINI_DATA_DIR / "mini_data.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    kind, root = module.mini_dir()  # made on first use (never committed)
    if kind != "broad":
        print(f"--quick: no BROAD, on the synthetic mini data in {root}", file=sys.stderr)
    return str(root)


def out_path(args, name: str):
    """Where the table goes: ``--out``; a full run without it: ``reports/bench/<name>``; quick: nowhere."""
    if args.out:
        return Path(args.out)
    return None if args.quick else BENCH_DIR / name


def interleaved_times(fns: dict, repeats: int) -> dict:
    """Wall times [s] of each callable in each of ``repeats`` rounds (a list per callable), alternating
    within each round (load from other processes hits all alike), after one untimed warm-up round (JIT,
    caches)."""
    for fn in fns.values():
        fn()
    times = {k: [] for k in fns}
    for _ in range(repeats):
        for k, fn in fns.items():
            t0 = time.perf_counter()
            fn()
            times[k].append(time.perf_counter() - t0)
    return times


def best_interleaved(fns: dict, repeats: int) -> dict:
    """Best wall time [s] of each callable over ``repeats`` interleaved rounds (``interleaved_times``)."""
    return {k: min(v) for k, v in interleaved_times(fns, repeats).items()}


def round_ratios(times: dict, key: str, ref: str) -> tuple[float, float, float]:
    """``(lowest, median, highest)`` over the rounds of ``interleaved_times`` of ``key``'s time over ``ref``'s
    in the same round: how far the ratio of the best times can be trusted on a machine whose speed moves."""
    r = np.asarray(times[key]) / np.asarray(times[ref])
    return float(r.min()), float(np.median(r)), float(r.max())


def vqf_batch(fs: float, gyr, acc, mag=None):
    """A callable running ``vqf.VQF(1/fs).updateBatch`` (9D, or 6D without ``mag``) on the arrays."""
    import vqf

    g, a = np.ascontiguousarray(gyr, float), np.ascontiguousarray(acc, float)
    m = None if mag is None else np.ascontiguousarray(mag, float)
    if m is None:
        return lambda: vqf.VQF(1.0 / fs).updateBatch(g, a)
    return lambda: vqf.VQF(1.0 / fs).updateBatch(g, a, m)


def context_note(what: str, args) -> str:
    """One paragraph for the table file: what was measured, on which machine and load."""
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    return (f"{what}. Measured {time.strftime('%Y-%m-%d %H:%M')} with togglecf {__version__} on "
            f"{os.cpu_count()} cores ({platform.machine()}, Python {platform.python_version()}), load average "
            f"{load:.1f} at the end{' (quick mode: mini data, not a measurement to quote)' if args.quick else ''}. "
            "Ratios are against `vqf.VQF.updateBatch` timed in the same run on the same samples; they move "
            "between runs by ±20 % or more on a shared machine.")


def finish(name: str, args, rows, columns, title: str, notes=(), digits: int = 3, ratios=None) -> dict:
    """Print the table, write it (``out_path``), return the result dict."""
    print()
    print(markdown_table(rows, columns, digits))
    path = out_path(args, name)
    paths = write_table(rows, path, columns, title, notes, digits) if path is not None else {}
    if paths:
        print(f"\nwrote {paths['md']} and {paths['csv']}")
    return {"rows": rows, "ratios": dict(ratios or {}), "paths": paths}
