"""Speed of the VQF core (``filters.vqf_core``) against the ``vqf`` package's C++ ``VQF.updateBatch``.

    .venv/bin/python pipelines/bench_vqf_core.py [--quick] [--trial NAME] [--repeats K] [--data DIR]

Both run on the same trial in the same process (9D, default parameters, Ts = 1/fs); each is
timed ``--repeats`` times, alternating, after one warm-up run (which also compiles the numba
kernel) and the best time is reported as µs per sample, with the ratio core / VQF. ``--quick`` uses the first
20 000 samples and 3 repeats (for the test suite); the full mode the whole trial and 15 repeats.
The two filters' outputs are compared as well (largest angle between them), so a fast but wrong
kernel does not pass unnoticed.
"""
from __future__ import annotations

import argparse
import math
import time

import numpy as np
import vqf

from togglecf.core import quaternion as quat
from togglecf.data.broad import DatasetIndex, resolve_data_dir
from togglecf.filters.vqf_core import VQFCoreFilter

DEFAULT_TRIAL = "21_undisturbed_fast_combined"


def _best_interleaved(fns, repeats):
    """Best wall time of each of ``fns`` over ``repeats`` rounds, the functions alternating
    within each round (so load from other processes hits both alike), after one warm-up round
    (numba compilation, caches). Returns ``[(best_s, last_output), ...]``."""
    outs = [fn() for fn in fns]
    best = [math.inf] * len(fns)
    for _ in range(repeats):
        for j, fn in enumerate(fns):
            t0 = time.perf_counter()
            outs[j] = fn()
            best[j] = min(best[j], time.perf_counter() - t0)
    return list(zip(best, outs))


def main(argv=None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--quick", action="store_true", help="first 20 000 samples, 3 repeats")
    p.add_argument("--trial", default=DEFAULT_TRIAL)
    p.add_argument("--repeats", type=int, default=None)
    p.add_argument("--data", default=None)
    args = p.parse_args(argv)
    index = DatasetIndex.from_dir(resolve_data_dir(args.data))
    t = index.load(args.trial)
    n = 20_000 if args.quick else len(t.gyr)
    repeats = args.repeats or (3 if args.quick else 15)
    g, a, m = (np.ascontiguousarray(x[:n], dtype=np.float64) for x in (t.gyr, t.acc, t.mag))
    ts = 1.0 / t.fs

    (t_core, q_core), (t_vqf, q_vqf) = _best_interleaved(
        [lambda: VQFCoreFilter(t.fs).update_batch(g, a, m).quat, lambda: vqf.VQF(ts).updateBatch(g, a, m)["quat9D"]],
        repeats)
    core_us, vqf_us = t_core / n * 1e6, t_vqf / n * 1e6
    max_angle = float(np.degrees(quat.angle_between(q_core, q_vqf)).max())
    print(f"{args.trial}: {n} samples at {t.fs:.1f} Hz, best of {repeats}")
    print(f"  core VQFCoreFilter.update_batch  {core_us:8.3f} µs/sample")
    print(f"  vqf  VQF.updateBatch (C++)       {vqf_us:8.3f} µs/sample")
    print(f"  ratio core / vqf                 {core_us / vqf_us:8.3f}")
    print(f"  max angle between outputs        {max_angle:8.5f}°")
    return {"n": n, "core_us": core_us, "vqf_us": vqf_us, "ratio": core_us / vqf_us, "max_angle_deg": max_angle}


if __name__ == "__main__":
    main()
