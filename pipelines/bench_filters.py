"""Speed of every classic togglecf filter (``filters.FILTERS``) next to VQF, imufusion and ahrs on one BROAD trial.

    .venv/bin/python pipelines/bench_filters.py [--quick] [--trial NAME] [--ahrs-samples 5000] [--repeats 3]
        [--out PATH]

Reports µs per sample (best of ``--repeats``, after JIT warm-up, all implementations of a mode
interleaved) and the ratio to ``vqf.VQF(Ts).updateBatch`` measured in the same run on the same
trial (9D rows against VQF 9D, 6D rows against VQF 6D). Goals: each togglecf filter ≤ 2× VQF;
ahrs (pure Python) ≥ 100× slower than ours. imufusion has no batch call, so it runs as a Python
loop over ``Ahrs.update`` (its C core plus the Python call overhead per sample).

Full run: trial 05, table in ``reports/bench/bench_filters.md``/``.csv``. ``--quick``: the mini
trial 02 (4000 samples), 1 repeat, ahrs on 200 samples.
"""
from __future__ import annotations

import argparse
import time

import numpy as np
from bench_common import add_common_args, best_interleaved, context_note, data_dir, finish, vqf_batch

from togglecf.data.broad import DatasetIndex, resolve_data_dir
from togglecf.filters import FILTERS

NAME = "bench_filters"
DEFAULT_TRIAL = "05_undisturbed_slow_rotation_with_breaks_B"
QUICK_TRIAL = "02"


def _ours(cls, fs, gyr, acc, mag):
    return lambda: cls(fs, use_mag=mag is not None).update_batch(gyr, acc, mag)


def main(argv=None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_common_args(p, NAME)
    p.add_argument("--trial", default=None, help=f"trial (default {DEFAULT_TRIAL}; --quick: {QUICK_TRIAL})")
    p.add_argument("--ahrs-samples", type=int, default=None, help="samples for the pure-Python ahrs runs "
                   "(default 5000; --quick 200)")
    p.add_argument("--repeats", type=int, default=None, help="default 3; --quick 1")
    args = p.parse_args(argv)
    index = DatasetIndex.from_dir(resolve_data_dir(data_dir(args)))
    trial = args.trial or (QUICK_TRIAL if args.quick else DEFAULT_TRIAL)
    t = index.load(index.select(trial)[0])
    gyr, acc, mag = (np.ascontiguousarray(x) for x in (t.gyr, t.acc, t.mag))
    n, fs = t.n_samples, t.fs
    repeats = args.repeats or (1 if args.quick else 3)
    ahrs_n = min(args.ahrs_samples or (200 if args.quick else 5000), n)
    print(f"trial {t.name}: {n} samples at {fs:.3f} Hz; best of {repeats} after warm-up")

    rows, ratios, us = [], {}, {}
    for mode, m in (("9D", mag), ("6D", None)):
        fns = {"vqf": vqf_batch(fs, gyr, acc, m)}
        for name, cls in FILTERS.items():
            fns[name] = _ours(cls, fs, gyr, acc, m)
        best = best_interleaved(fns, repeats)
        ref = 1e6 * best["vqf"] / n
        us[("vqf", mode)] = ref
        rows.append({"implementation": "vqf (VQF.updateBatch, C++)", "mode": mode, "us_per_sample": ref,
                     "ratio_to_vqf": 1.0})
        for name in FILTERS:
            v = 1e6 * best[name] / n
            us[(name, mode)] = v
            ratios[f"{name} {mode}"] = v / ref
            rows.append({"implementation": f"togglecf {name}", "mode": mode, "us_per_sample": v,
                         "ratio_to_vqf": v / ref})
    ref9 = us[("vqf", "9D")]

    try:
        import imufusion

        gd, ag = np.degrees(gyr), acc / 9.81  # imufusion wants °/s and g

        def run_fusion():
            a = imufusion.Ahrs().set_sample_period(1.0 / fs)
            for k in range(n):
                a.update(gd[k], ag[k], mag[k])
        tf = 1e6 * best_interleaved({"f": run_fusion}, 1)["f"] / n
        ratios["imufusion 9D"] = tf / ref9
        rows.append({"implementation": "imufusion (Python loop over Ahrs.update)", "mode": "9D", "us_per_sample": tf,
                     "ratio_to_vqf": tf / ref9})
    except ImportError:
        print("imufusion not installed")

    try:
        from ahrs.filters import Madgwick, Mahony

        for label, cls, kw in (("madgwick", Madgwick, dict(gain=0.1)), ("mahony", Mahony, dict(k_P=0.7, k_I=0.01))):
            def run_ahrs():
                f = cls(frequency=fs, **kw)
                q = np.array([1.0, 0.0, 0.0, 0.0])
                for k in range(ahrs_n):
                    q = f.updateMARG(q, gyr[k], acc[k], mag[k])
            t0 = time.perf_counter()
            run_ahrs()
            ta = 1e6 * (time.perf_counter() - t0) / ahrs_n
            ratios[f"ahrs {label} 9D"] = ta / ref9
            rows.append({"implementation": f"ahrs {label} (pure Python, {ahrs_n} samples)", "mode": "9D",
                         "us_per_sample": ta, "ratio_to_vqf": ta / ref9})
            print(f"ahrs {label} / togglecf {label}: {ta / us[(label, '9D')]:.0f}x")
    except ImportError:
        print("ahrs not installed")

    slow = [k for k, r in ratios.items() if k.split()[0] in FILTERS and r > 2.0]
    res = finish(NAME, args, rows, ["implementation", "mode", "us_per_sample", "ratio_to_vqf"],
                 "Filter speed against VQF",
                 [context_note(f"Trial {t.name} ({n} samples at {fs:.1f} Hz), each filter's `update_batch` on the "
                               f"whole trial, best of {repeats} interleaved runs after a warm-up; 9D rows against "
                               "VQF 9D, 6D rows against VQF 6D", args)],
                 ratios=ratios)
    print("\nall togglecf filters within 2x VQF" if not slow else f"\nslower than 2x VQF: {slow}")
    return res


if __name__ == "__main__":
    main()
