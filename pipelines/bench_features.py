"""Feature-extraction throughput (``features.compute_features``, one core) against VQF on the same samples.

    .venv/bin/python pipelines/bench_features.py [--quick] [--trials 05] [--hop 0.05] [--window 0.2] [--repeats 5]
        [--synthetic] [--out PATH]

Data: the first five BROAD trials present, concatenated (``--trials`` chooses others); with
``--synthetic`` or without BROAD, a random 1,000,000-sample recording. Reported: µs per sample and
samples/s (best of ``--repeats``, interleaved with ``vqf.VQF.updateBatch`` on the same arrays, after
a warm-up) and the ratio features ÷ VQF. Full run: table in ``reports/bench/bench_features.md``/``.csv``.
``--quick``: the three mini trials (``tests/data/broad_mini``, or ``synthetic_mini`` without BROAD; 12 000 samples), 2 repeats.
"""
from __future__ import annotations

import argparse
import os

os.environ.setdefault("OMP_NUM_THREADS", "1")

import numpy as np  # noqa: E402
from bench_common import add_common_args, best_interleaved, context_note, data_dir, finish, vqf_batch  # noqa: E402

from togglecf.data.broad import DatasetIndex, resolve_data_dir  # noqa: E402
from togglecf.features.windows import FeatureSettings, compute_features  # noqa: E402

NAME = "bench_features"
FS_SYNTHETIC = 285.714


def _data(args):
    if not args.synthetic:
        try:
            index = DatasetIndex.from_dir(resolve_data_dir(data_dir(args)))
            names = index.select(args.trials) if args.trials else index.select()[:5]
            parts = [index.load(n) for n in names]
            gyr, acc, mag = (np.concatenate([getattr(t, k) for t in parts]) for k in ("gyr", "acc", "mag"))
            return gyr, acc, mag, parts[0].fs, f"{len(parts)} BROAD trials concatenated ({', '.join(names)})"
        except Exception as exc:  # no data: fall back to synthetic
            print(f"(BROAD not used: {exc})")
    rng = np.random.default_rng(0)
    n = 20_000 if args.quick else 1_000_000
    gyr = rng.standard_normal((n, 3))
    acc = rng.standard_normal((n, 3)) + [0, 0, 9.81]
    mag = rng.standard_normal((n, 3)) + [0, 20, -40]
    return gyr, acc, mag, FS_SYNTHETIC, "synthetic random recording"


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_common_args(ap, NAME)
    ap.add_argument("--trials", default=None, help="comma-separated trials (default: the first five present)")
    ap.add_argument("--hop", type=float, default=0.05)
    ap.add_argument("--window", type=float, default=0.2)
    ap.add_argument("--repeats", type=int, default=None, help="default 5; --quick 2")
    ap.add_argument("--synthetic", action="store_true", help="use random data even if BROAD is present")
    args = ap.parse_args(argv)
    repeats = args.repeats or (2 if args.quick else 5)
    s = FeatureSettings(window_s=args.window, hop_s=args.hop)
    gyr, acc, mag, fs, src = _data(args)
    gyr, acc, mag = (np.ascontiguousarray(x, float) for x in (gyr, acc, mag))
    n = gyr.shape[0]
    shape = {}

    def feats():
        shape["X"] = compute_features(gyr, acc, mag, fs, s)[0].shape

    best = best_interleaved({"features": feats, "vqf": vqf_batch(fs, gyr, acc, mag)}, repeats)
    us = {k: 1e6 * v / n for k, v in best.items()}
    ratio = us["features"] / us["vqf"]
    what = (f"{src}: {n:,} samples at {fs:.1f} Hz; window {args.window} s, hop {args.hop} s -> {shape['X'][0]:,} "
            f"windows x {shape['X'][1]} features; one thread; best of {repeats} interleaved runs after a warm-up")
    print(what)
    rows = [{"step": "vqf (VQF.updateBatch, C++, 9D)", "us_per_sample": us["vqf"],
             "samples_per_s": round(1e6 / us["vqf"]),
             "ratio_to_vqf": 1.0},
            {"step": "togglecf compute_features (vectorised, all windows)", "us_per_sample": us["features"],
             "samples_per_s": round(1e6 / us["features"]), "ratio_to_vqf": ratio}]
    return finish(NAME, args, rows, ["step", "us_per_sample", "samples_per_s", "ratio_to_vqf"],
                  "Feature extraction speed against VQF", [context_note(what, args)], ratios={"features": ratio})


if __name__ == "__main__":
    main()
