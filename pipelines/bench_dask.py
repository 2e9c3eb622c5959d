"""Scaling of a fixed filter sweep on Dask: LocalCluster with 1, 2 and 4 worker processes.

    python pipelines/bench_dask.py [--data DIR] [--trials LIST] [--workers 1,2,4] [--grid Kp=...] [--out FILE.json]

The sweep: a Mahony grid (default 7 x 6 = 42 points) on every selected BROAD trial (default all).
Reference measured in the same run: the local backend (fork process pool on all cores, one task per
trial). Each cluster is started (workers on 127.0.0.1, one thread each) and warmed up (imports, numba
kernels from the cache, one trial loaded) before the timed sweep. Reported: seconds, speedup over one
worker, efficiency = speedup / workers, and efficiency against what the machine can give
(speedup / min(workers, cores)): with 2 cores, 4 worker processes cannot beat 2.
"""
from __future__ import annotations

import argparse
import logging
import os
import sys
import time

from togglecf.core.io import atomic_write_json
from togglecf.data.broad import DatasetIndex, resolve_data_dir
from togglecf.parallel.backend import DaskBackend, LocalBackend
from togglecf.run.scoring import grid_points, parse_grid
from togglecf.run.sweep import run_sweep


def _sweep(index, names, params, backend, chunk_size):
    t0 = time.perf_counter()
    r = run_sweep(index, names, "mahony", params, backend=backend, chunk_size=chunk_size, on_error="raise",
                  desc="bench")
    return time.perf_counter() - t0, r


def _cpu():
    t = os.times()
    return t.user + t.system


def _totals(r):
    return [[res[n].errors["total"] for n in sorted(res)] for res in r.results]


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--data", metavar="DIR")
    p.add_argument("--trials", default=None, help="comma-separated trial numbers (default: all present)")
    p.add_argument("--workers", default="1,2,4")
    p.add_argument("--grid", action="append", default=None, metavar="NAME=SPEC",
                   help="Mahony grid (default Kp=0.4:1.0:0.1, Ki=0,0.0005,0.001,0.0015,0.002,0.003)")
    p.add_argument("--chunk-size", type=int, default=0, help="grid points per Dask task (0: automatic)")
    p.add_argument("--repeat", type=int, default=1, help="time each setting N times, report the best")
    p.add_argument("--out", metavar="JSON", help="also write the numbers here")
    args = p.parse_args(argv)
    from distributed import Client, LocalCluster

    index = DatasetIndex.from_dir(resolve_data_dir(args.data))
    names = index.select(args.trials)
    grid = parse_grid(args.grid or ["Kp=0.4:1.0:0.1", "Ki=0,0.0005,0.001,0.0015,0.002,0.003"])
    params = grid_points(grid)
    cores = os.cpu_count() or 1
    print(f"sweep: mahony, {len(params)} grid points x {len(names)} trials = {len(params) * len(names)} "
          f"filter runs; machine: {cores} cores", flush=True)

    print(f"load average before: {os.getloadavg()[0]:.2f} (other processes on the machine skew the times)")
    runs = [_sweep(index, names, params, LocalBackend(), None) for _ in range(args.repeat)]
    t_local, ref = min(r[0] for r in runs), runs[0][1]
    print(f"local backend (process pool, {cores} processes): {t_local:.1f} s", flush=True)
    rows = []
    for n in [int(x) for x in args.workers.split(",")]:
        with LocalCluster(n_workers=n, threads_per_worker=1, processes=True, host="127.0.0.1",
                          dashboard_address=None, silence_logs=logging.CRITICAL) as cluster, Client(cluster) as client:
            client.wait_for_workers(n)
            be = DaskBackend(client)
            _sweep(index, names[: max(1, n)], params[:1], be, 1)  # warm-up: imports, kernels, one trial
            c0 = client.run(_cpu)
            runs = [_sweep(index, names, params, be, args.chunk_size) for _ in range(args.repeat)]
            c1 = client.run(_cpu)
            t, r = min(x[0] for x in runs), runs[0][1]
            cpu = sum(c1[w] - c0[w] for w in c0 if w in c1) / args.repeat
        assert _totals(r) == _totals(ref), "dask results differ from the local backend"
        rows.append({"workers": n, "seconds": t, "cores_used": cpu / t})
        print(f"dask, {n} worker process(es): {t:.1f} s, workers' CPU time {cpu:.1f} s", flush=True)
    t1 = next((r["seconds"] for r in rows if r["workers"] == 1), None)
    print(f"\n{'workers':>7} {'seconds':>8} {'speedup':>8} {'efficiency':>10} {'eff. vs cores':>13} {'cores used':>10}"
          f"  (local backend: {t_local:.1f} s)")
    for r in rows:
        if t1:
            r["speedup"] = t1 / r["seconds"]
            r["efficiency"] = r["speedup"] / r["workers"]
            r["efficiency_vs_cores"] = r["speedup"] / min(r["workers"], cores)
            print(f"{r['workers']:>7d} {r['seconds']:>8.1f} {r['speedup']:>8.2f} {r['efficiency']:>10.0%} "
                  f"{r['efficiency_vs_cores']:>13.0%} {r['cores_used']:>10.2f}")
        else:
            print(f"{r['workers']:>7d} {r['seconds']:>8.1f}")
    if any(r["workers"] > cores for r in rows):
        print(f"\nnote: this machine has {cores} cores, so more than {cores} worker processes share them: the "
              f"ideal speedup is min(workers, {cores}); 'efficiency' is against workers, 'eff. vs cores' "
              f"against min(workers, cores).")
    print("cores used = the workers' CPU seconds / wall seconds: below min(workers, cores) when other processes "
          "take CPU time or the tasks cannot keep the workers busy.")
    print("all Dask results equal the local backend's (bit for bit).")
    print(f"load average after: {os.getloadavg()[0]:.2f}; best of {args.repeat} run(s) per setting")
    if args.out:
        atomic_write_json(args.out, {"grid_points": len(params), "trials": names, "cores": cores,
                                     "local_seconds": t_local, "dask": rows})
    return 0


if __name__ == "__main__":
    sys.exit(main())
