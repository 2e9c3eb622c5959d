"""Feature-extraction throughput: prints samples/s (one core) for a real BROAD trial when present,
else for a synthetic 1-million-sample recording.

    .venv/bin/python pipelines/bench_features.py [--hop 0.05] [--window 0.2] [--repeat 5]
"""
from __future__ import annotations

import argparse
import os
import time

os.environ.setdefault("OMP_NUM_THREADS", "1")

import numpy as np  # noqa: E402

from togglecf.features.windows import FeatureSettings, compute_features  # noqa: E402


def main():
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--hop", type=float, default=0.05)
    ap.add_argument("--window", type=float, default=0.2)
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--synthetic", action="store_true", help="use random data even if BROAD is present")
    args = ap.parse_args()
    s = FeatureSettings(window_s=args.window, hop_s=args.hop)
    fs = 285.714
    src = "synthetic 1,000,000 samples"
    gyr = acc = mag = None
    if not args.synthetic:
        try:
            from togglecf.data.broad import DatasetIndex, resolve_data_dir

            index = DatasetIndex.from_dir(resolve_data_dir())
            parts = [index.load(n) for n in index.select()[:5]]
            gyr, acc, mag = (np.concatenate([getattr(t, k) for t in parts]) for k in ("gyr", "acc", "mag"))
            fs = parts[0].fs
            src = f"{len(parts)} BROAD trials concatenated, {gyr.shape[0]:,} samples"
        except Exception as exc:  # no data: fall back to synthetic
            print(f"(BROAD not used: {exc})")
    if gyr is None:
        rng = np.random.default_rng(0)
        n = 1_000_000
        gyr = rng.standard_normal((n, 3))
        acc = rng.standard_normal((n, 3)) + [0, 0, 9.81]
        mag = rng.standard_normal((n, 3)) + [0, 20, -40]
    compute_features(gyr[:5000], acc[:5000], mag[:5000], fs, s)  # warm-up
    times = []
    for _ in range(args.repeat):
        t0 = time.perf_counter()
        X, ends = compute_features(gyr, acc, mag, fs, s)
        times.append(time.perf_counter() - t0)
    best, med = min(times), float(np.median(times))
    n = gyr.shape[0]
    print(f"{src}; window {args.window} s, hop {args.hop} s -> {X.shape[0]:,} windows x {X.shape[1]} features")
    print(f"best {best * 1e3:.1f} ms, median {med * 1e3:.1f} ms over {args.repeat} runs")
    print(f"samples/s: {n / best:,.0f} (best), {n / med:,.0f} (median)")


if __name__ == "__main__":
    main()
