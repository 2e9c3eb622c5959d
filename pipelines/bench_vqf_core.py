"""Speed of the VQF core (``filters.vqf_core``) against the ``vqf`` package's C++ ``VQF.updateBatch``.

    .venv/bin/python pipelines/bench_vqf_core.py [--quick] [--trial NAME] [--repeats K] [--data DIR] [--out PATH]

Both run on the same trial in the same process (9D and 6D, default parameters, Ts = 1/fs); each
is timed ``--repeats`` times, alternating, after one warm-up run (which also compiles the numba
kernel) and the best time is reported as µs per sample, with the ratio core / VQF. The two
filters' outputs are compared as well (largest angle between them), so a fast but wrong kernel
does not pass unnoticed. Full run: trial 21 (whole), 15 repeats, table in
``reports/bench/bench_vqf_core.md``/``.csv``. ``--quick``: the mini trial 07 (or, with
``--data``, the given trial) cut to 20 000 samples, 3 repeats.
"""
from __future__ import annotations

import argparse

import numpy as np
import vqf
from bench_common import add_common_args, best_interleaved, context_note, data_dir, finish

from togglecf.core import quaternion as quat
from togglecf.data.broad import DatasetIndex, resolve_data_dir
from togglecf.filters.vqf_core import VQFCoreFilter

NAME = "bench_vqf_core"
DEFAULT_TRIAL = "21_undisturbed_fast_combined"
QUICK_TRIAL = "07"  # in the mini data (fast rotation; tests/data/broad_mini or synthetic_mini)


def main(argv=None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_common_args(p, NAME)
    p.add_argument("--trial", default=None, help=f"trial number or name (default {DEFAULT_TRIAL}; --quick: "
                   f"{QUICK_TRIAL}, or {DEFAULT_TRIAL} when --data is given)")
    p.add_argument("--repeats", type=int, default=None)
    args = p.parse_args(argv)
    index = DatasetIndex.from_dir(resolve_data_dir(data_dir(args)))
    trial = args.trial or (QUICK_TRIAL if args.quick and not args.data else DEFAULT_TRIAL)
    t = index.load(index.select(trial)[0])
    n = min(20_000, t.n_samples) if args.quick else t.n_samples
    repeats = args.repeats or (3 if args.quick else 15)
    g, a, m = (np.ascontiguousarray(x[:n], dtype=np.float64) for x in (t.gyr, t.acc, t.mag))
    ts = 1.0 / t.fs
    outs = {}

    def run(key, fn):
        def go():
            outs[key] = fn()
        return go

    fns = {
        "core 9D": run("core 9D", lambda: VQFCoreFilter(t.fs).update_batch(g, a, m).quat),
        "vqf 9D": run("vqf 9D", lambda: vqf.VQF(ts).updateBatch(g, a, m)["quat9D"]),
        "core 6D": run("core 6D", lambda: VQFCoreFilter(t.fs, use_mag=False).update_batch(g, a, None).quat),
        "vqf 6D": run("vqf 6D", lambda: vqf.VQF(ts).updateBatch(g, a)["quat6D"]),
    }
    best = best_interleaved(fns, repeats)
    us = {k: v / n * 1e6 for k, v in best.items()}
    rows, ratios = [], {}
    print(f"{t.name}: {n} samples at {t.fs:.1f} Hz, best of {repeats}")
    for mode in ("9D", "6D"):
        angle = float(np.nanmax(np.degrees(quat.angle_between(outs[f"core {mode}"], outs[f"vqf {mode}"]))))
        ratios[f"vqf_core {mode}"] = us[f"core {mode}"] / us[f"vqf {mode}"]
        rows.append({"implementation": "vqf (VQF.updateBatch, C++)", "mode": mode, "us_per_sample": us[f"vqf {mode}"],
                     "ratio_to_vqf": 1.0, "max_angle_deg": None})
        rows.append({"implementation": "togglecf vqf_core (numba)", "mode": mode, "us_per_sample": us[f"core {mode}"],
                     "ratio_to_vqf": ratios[f"vqf_core {mode}"], "max_angle_deg": angle})
    res = finish(NAME, args, rows, ["implementation", "mode", "us_per_sample", "ratio_to_vqf", "max_angle_deg"],
                 "VQF core against the vqf package",
                 [context_note(f"Trial {t.name}, {n} samples at {t.fs:.1f} Hz, best of {repeats} interleaved runs "
                               "after a warm-up; max_angle_deg: largest angle between the two outputs", args)],
                 digits=4, ratios=ratios)
    # the keys tests/test_vqf_core.py reads (9D)
    res.update(n=n, core_us=us["core 9D"], vqf_us=us["vqf 9D"], ratio=us["core 9D"] / us["vqf 9D"],
               max_angle_deg=rows[1]["max_angle_deg"])
    print(f"\nratio core / vqf (9D): {res['ratio']:.3f}")
    return res


if __name__ == "__main__":
    main()
