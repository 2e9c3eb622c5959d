"""Scaling of a fixed filter sweep on Dask: LocalCluster with 1, 2 and 4 worker processes.

    python pipelines/bench_dask.py [--quick] [--data DIR] [--trials LIST] [--workers 1,2,4] [--grid Kp=...] [--out PATH]

The sweep: a Mahony grid (default 7 x 6 = 42 points) on every selected BROAD trial (default all).
Reference measured in the same run: the local backend (fork process pool on all cores, one task per
trial). Each cluster is started (workers on 127.0.0.1, one thread each) and warmed up (imports, numba
kernels from the cache, one trial loaded) before the timed sweep. Reported: seconds, speedup over one
worker, efficiency = speedup / workers, and efficiency against what the machine can give
(speedup / min(workers, cores)): with 2 cores, 4 worker processes cannot beat 2.

Against VQF, in the same run on the same trials: ``vqf.VQF.updateBatch`` and Mahony's own
``update_batch`` are timed once over every trial in this process (best of 3); ``us_per_run_sample``
is a sweep's wall time per filter run and sample (seconds / (points x samples of all trials)), and
``ratio_to_vqf`` divides it by VQF's µs per sample: the price of one grid point's filter run, all
overheads (loading, scheduling, scoring) included, in VQF calls on one core.
Full run: table in ``reports/bench/bench_dask.md``/``.csv``. ``--quick``: the mini data, a 2-point
grid, one worker.
"""
from __future__ import annotations

import argparse
import logging
import os
import time

import numpy as np
from bench_common import add_common_args, best_interleaved, context_note, data_dir, finish, vqf_batch

from togglecf.data.broad import DatasetIndex, resolve_data_dir
from togglecf.filters import make_filter
from togglecf.parallel.backend import DaskBackend, LocalBackend
from togglecf.run.scoring import grid_points, parse_grid
from togglecf.run.sweep import run_sweep

NAME = "bench_dask"
DEFAULT_GRID = ["Kp=0.4:1.0:0.1", "Ki=0,0.0005,0.001,0.0015,0.002,0.003"]
QUICK_GRID = ["Kp=0.5,0.7", "Ki=0"]


def _sweep(index, names, params, backend, chunk_size):
    t0 = time.perf_counter()
    r = run_sweep(index, names, "mahony", params, backend=backend, chunk_size=chunk_size, on_error="raise")
    return time.perf_counter() - t0, r


def _cpu(client) -> dict:
    """CPU seconds (user + system) of every worker process. ``os.times`` itself is sent, not a function
    of this script: the workers cannot import ``bench_dask`` when it is imported rather than run."""
    return {w: t[0] + t[1] for w, t in client.run(os.times).items()}


def _totals(r):
    return [[res[n].errors["total"] for n in sorted(res)] for res in r.results]


def _serial_us(index, names, repeats=3):
    """µs per sample of VQF and of Mahony (default settings) over every trial, in this process."""
    trials = [index.load(n) for n in names]
    total = {"vqf": 0.0, "mahony": 0.0}
    for t in trials:
        g, a, m = (np.ascontiguousarray(x) for x in (t.gyr, t.acc, t.mag))
        best = best_interleaved({"vqf": vqf_batch(t.fs, g, a, m),
                                 "mahony": lambda: make_filter("mahony", t.fs).update_batch(g, a, m)}, repeats)
        for k in total:
            total[k] += best[k]
    n = sum(t.n_samples for t in trials)
    return {k: 1e6 * v / n for k, v in total.items()}, n


def main(argv=None) -> dict:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_common_args(p, NAME)
    p.add_argument("--trials", default=None, help="comma-separated trial numbers (default: all present)")
    p.add_argument("--workers", default=None, help="worker processes to try (default 1,2,4; --quick 1)")
    p.add_argument("--grid", action="append", default=None, metavar="NAME=SPEC",
                   help="Mahony grid (default Kp=0.4:1.0:0.1, Ki=0,0.0005,0.001,0.0015,0.002,0.003; --quick: 2 points)")
    p.add_argument("--chunk-size", type=int, default=0, help="grid points per Dask task (0: automatic)")
    p.add_argument("--repeat", type=int, default=1, help="time each setting N times, report the best")
    args = p.parse_args(argv)
    from distributed import Client, LocalCluster

    index = DatasetIndex.from_dir(resolve_data_dir(data_dir(args)))
    names = index.select(args.trials)
    grid = parse_grid(args.grid or (QUICK_GRID if args.quick else DEFAULT_GRID))
    params = grid_points(grid)
    workers = [int(x) for x in (args.workers or ("1" if args.quick else "1,2,4")).split(",")]
    cores = os.cpu_count() or 1
    print(f"sweep: mahony, {len(params)} grid points x {len(names)} trials = {len(params) * len(names)} "
          f"filter runs; machine: {cores} cores", flush=True)
    serial, n_samples = _serial_us(index, names, 1 if args.quick else 3)
    print(f"serial, this process: vqf {serial['vqf']:.3f} µs/sample, mahony {serial['mahony']:.3f} µs/sample "
          f"({n_samples:,} samples)")

    print(f"load average before: {os.getloadavg()[0]:.2f} (other processes on the machine skew the times)")
    runs = [_sweep(index, names, params, LocalBackend(), None) for _ in range(args.repeat)]
    t_local, ref = min(r[0] for r in runs), runs[0][1]
    print(f"local backend (process pool, {cores} processes): {t_local:.1f} s", flush=True)
    per_run = lambda sec: 1e6 * sec / (len(params) * n_samples)  # noqa: E731  µs per filter run and sample
    rows = [{"backend": f"local (process pool, {cores} processes)", "workers": cores, "seconds": t_local,
             "speedup": None, "efficiency": None, "efficiency_vs_cores": None, "cores_used": None,
             "us_per_run_sample": per_run(t_local), "ratio_to_vqf": per_run(t_local) / serial["vqf"]}]
    for n in workers:
        with LocalCluster(n_workers=n, threads_per_worker=1, processes=True, host="127.0.0.1",
                          dashboard_address=None, silence_logs=logging.CRITICAL) as cluster, Client(cluster) as client:
            client.wait_for_workers(n)
            be = DaskBackend(client)
            _sweep(index, names[: max(1, n)], params[:1], be, 1)  # warm-up: imports, kernels, one trial
            c0 = _cpu(client)
            runs = [_sweep(index, names, params, be, args.chunk_size) for _ in range(args.repeat)]
            c1 = _cpu(client)
            t, r = min(x[0] for x in runs), runs[0][1]
            cpu = sum(c1[w] - c0[w] for w in c0 if w in c1) / args.repeat
        assert _totals(r) == _totals(ref), "dask results differ from the local backend"
        rows.append({"backend": f"dask, {n} worker process(es)", "workers": n, "seconds": t, "cores_used": cpu / t,
                     "us_per_run_sample": per_run(t), "ratio_to_vqf": per_run(t) / serial["vqf"]})
        print(f"dask, {n} worker process(es): {t:.1f} s, workers' CPU time {cpu:.1f} s", flush=True)
    t1 = next((r["seconds"] for r in rows[1:] if r["workers"] == 1), None)
    for r in rows[1:]:
        if t1:
            r["speedup"] = t1 / r["seconds"]
            r["efficiency"] = r["speedup"] / r["workers"]
            r["efficiency_vs_cores"] = r["speedup"] / min(r["workers"], cores)
    notes = [context_note(f"Mahony sweep, {len(params)} grid points x {len(names)} trials ({n_samples:,} samples); "
                          f"best of {args.repeat} run(s) per setting. Serially in one process: VQF "
                          f"{serial['vqf']:.3f} µs/sample, Mahony {serial['mahony']:.3f} µs/sample. "
                          "us_per_run_sample = wall time / (grid points x samples); ratio_to_vqf = that ÷ VQF's "
                          "µs/sample; cores_used = the workers' CPU seconds / wall seconds", args)]
    if any(w > cores for w in workers):
        notes.append(f"This machine has {cores} cores, so more than {cores} worker processes share them: the ideal "
                     f"speedup is min(workers, {cores}); efficiency is against workers, efficiency_vs_cores against "
                     "min(workers, cores).")
    res = finish(NAME, args, rows, ["backend", "workers", "seconds", "speedup", "efficiency", "efficiency_vs_cores",
                                    "cores_used", "us_per_run_sample", "ratio_to_vqf"],
                 "Dask scaling of a filter sweep", notes, digits=3,
                 ratios={r["backend"]: r["ratio_to_vqf"] for r in rows}
                 | {"mahony serial": serial["mahony"] / serial["vqf"]})
    print("all Dask results equal the local backend's (bit for bit).")
    print(f"load average after: {os.getloadavg()[0]:.2f}; best of {args.repeat} run(s) per setting")
    return res


if __name__ == "__main__":
    main()
