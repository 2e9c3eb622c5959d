"""Speed of every registered togglecf filter next to VQF, imufusion and ahrs on one BROAD trial.

    .venv/bin/python pipelines/bench_filters.py [--trial NAME] [--ahrs-samples 5000]

Reports µs per sample (best of 3, after JIT warm-up) and the ratio to ``vqf.VQF(Ts).updateBatch``
measured in the same run. Goals: each togglecf filter ≤ 2× VQF; ahrs (pure Python) ≥ 100×
slower than ours. imufusion has no batch call, so it runs as a Python loop over
``Ahrs.update`` (its C core plus the Python call overhead per sample).
"""
from __future__ import annotations

import argparse
import time

import numpy as np

from togglecf.data.broad import DatasetIndex, resolve_data_dir
from togglecf.filters import FILTERS


def best_of(fn, repeats=3):
    best = np.inf
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return best


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--data", default=None)
    p.add_argument("--trial", default="05_undisturbed_slow_rotation_with_breaks_B")
    p.add_argument("--ahrs-samples", type=int, default=5000)
    args = p.parse_args(argv)
    trial = DatasetIndex.from_dir(resolve_data_dir(args.data)).load(args.trial)
    gyr, acc, mag = (np.ascontiguousarray(x) for x in (trial.gyr, trial.acc, trial.mag))
    n, fs = trial.n_samples, trial.fs
    print(f"trial {trial.name}: {n} samples at {fs:.3f} Hz; best of 3 after warm-up")
    rows = []  # (name, mode, µs/sample)

    import vqf
    t = best_of(lambda: vqf.VQF(1.0 / fs).updateBatch(gyr, acc, mag))
    t_vqf = 1e6 * t / n
    rows.append(("vqf (VQF.updateBatch)", "9D", t_vqf))

    ours = {}
    for name, cls in FILTERS.items():
        for use_mag in (True, False):
            m = mag if use_mag else None
            cls(fs, use_mag=use_mag).update_batch(gyr[:10], acc[:10], None if m is None else m[:10])  # JIT warm-up
            t = best_of(lambda: cls(fs, use_mag=use_mag).update_batch(gyr, acc, m))
            ours[(name, use_mag)] = 1e6 * t / n
            rows.append((f"togglecf {name}", "9D" if use_mag else "6D", 1e6 * t / n))

    try:
        import imufusion
        gd, ag = np.degrees(gyr), acc / 9.81  # imufusion wants °/s and g

        def run_fusion():
            a = imufusion.Ahrs().set_sample_period(1.0 / fs)
            for k in range(n):
                a.update(gd[k], ag[k], mag[k])
        rows.append(("imufusion (Python loop over Ahrs.update)", "9D", 1e6 * best_of(run_fusion) / n))
    except ImportError:
        print("imufusion not installed")

    try:
        from ahrs.filters import Madgwick, Mahony
        k_n = min(args.ahrs_samples, n)
        for label, cls, kw in (("madgwick", Madgwick, dict(gain=0.1)), ("mahony", Mahony, dict(k_P=0.7, k_I=0.01))):
            def run_ahrs():
                f = cls(frequency=fs, **kw)
                q = np.array([1.0, 0.0, 0.0, 0.0])
                for k in range(k_n):
                    q = f.updateMARG(q, gyr[k], acc[k], mag[k])
            t = 1e6 * best_of(run_ahrs, repeats=1 if k_n > 2000 else 3) / k_n
            rows.append((f"ahrs {label} (pure Python, {k_n} samples)", "9D", t))
            ours_t = ours.get((label, True))
            if ours_t:
                print(f"ahrs {label} / togglecf {label}: {t / ours_t:.0f}x")
    except ImportError:
        print("ahrs not installed")

    print(f"\n{'implementation':48s} {'mode':4s} {'µs/sample':>10s} {'÷ VQF':>8s}")
    for name, mode, us in rows:
        print(f"{name:48s} {mode:4s} {us:10.3f} {us / t_vqf:8.2f}")
    slow = [(f"{name} {mode}", us / t_vqf) for name, mode, us in rows if name.startswith("togglecf") and us > 2 * t_vqf]
    print("\nall togglecf filters within 2x VQF" if not slow else f"\nslower than 2x VQF: {slow}")


if __name__ == "__main__":
    main()
