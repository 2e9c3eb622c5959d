"""Cycles per sample of the exported C filters on a Cortex-M4F: an estimate from an instruction-set
emulator, not a measurement on the hardware (``togglecf.embedded.cycles``).

    python pipelines/bench_cycles.py [--quick] [--models DIR] [--trial 21] [--samples N] [--opt -O2 -Os]
                                     [--clock-mhz 168] [--data DIR] [--out PATH]

Each filter is exported as ``togglecf export`` writes it (the VQF core ``tcf_vqf.c`` 9D and 6D; the
learned VQF ``tcf_vqf_toggling.c`` with the pretrained model as shipped (its learned settings; the core alone
where it learns nothing), with the
pretrained model's trees and learning on (``bench_learned_vqf.learning_on_model``: its 240 class
trees every 0.1 s, the size ``togglecf train --from-pretrained`` makes), and with a trained model
directory's trees in the loop, in the default array layout and in the complete one
(``--forest-layout``); the toggling CF ``tcf_filter.c``), compiled with ``arm-none-eabi-gcc`` for the
Cortex-M4F (``-mcpu=cortex-m4 -mthumb -mfpu=fpv4-sp-d16 -mfloat-abi=hard``, at each ``--opt``),
linked bare-metal with newlib's libm, and run one update per sample on the first ``--samples`` of a
BROAD trial in the emulator (unicorn), which counts the executed instructions; the cycles are
priced with the Cortex-M4 TRM's instruction timings at zero wait states (``CycleModel``; a range
for the branch refill P = 1-3). Each row also checks the emulated build against the host build of
the same export on the same samples (largest angle between their orientations). Each filter also runs,
exported at that rate, on the same samples every 3 averaged (``bench_learned_vqf.LOW_RATE_FACTOR``: 95.2 Hz, a
phone's rate): its mean cycles there and their share of that sample period. The learned filters' models predict
every 0.1 s at any rate, so at a lower rate a sample carries more of their cycles.

Full run: trial 21, 2000 samples, -O2 and -Os, table in ``reports/bench/bench_cycles.md``/``.csv``;
without ``--models`` a small model directory (10 + 10 trees of depth 4, small gain grids) is trained
first on four BROAD trials (about a minute), so the trees run in the loop. ``--quick``: 200 samples of
the mini trial 07, -O2, the VQF core and the pretrained learned VQF (plus the trained filters with
``--models``; not the learning-on row). Needs the ARM cross compiler and the ``embedded`` extra (unicorn, capstone).
"""
from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

import numpy as np
from bench_common import add_common_args, data_dir, finish
from bench_learned_vqf import LEARNED_TAU_ACC, LOW_RATE_FACTOR, learning_on_model

from togglecf.core import quaternion as quat
from togglecf.data.broad import DatasetIndex, resolve_data_dir
from togglecf.embedded import cfilter, cvqf, cvqf_toggling, cycles
from togglecf.run.config import load_config
from togglecf.run.transfer import decimate_trial
from togglecf.run.train import run_training
from togglecf.toggling.pretrained import PRETRAINED_FILE

#: the learning-on row's settings, as bench_learned_vqf's
LEARNING_ON = f"τ_acc per state {LEARNED_TAU_ACC[0]:g} to {LEARNED_TAU_ACC[1]:g} s"

NAME = "bench_cycles"
DEFAULT_TRIAL = "21_undisturbed_fast_combined"
QUICK_TRIAL = "07"
TRAIN_TRIALS = "02,07,21,24"
COLUMNS = ["filter", "opt", "samples", "instructions_mean", "instructions_max", "cycles_mean", "cycles_max",
           "cycles_range_mean", "cycles_range_max", "us_mean", "load_285.7_mean_pct", "load_285.7_max_pct",
           "ratio_to_vqf", "max_angle_deg"]


def low_rate_columns(fs_low: float) -> list:
    """The columns of the low-rate run at ``fs_low`` [Hz]: its mean cycles a sample and their share of its period."""
    return [f"cycles_mean_{fs_low:.1f}", f"load_{fs_low:.1f}_mean_pct"]


def table_columns(fs_low: float) -> list:
    """The table's columns: ``COLUMNS`` with ``low_rate_columns(fs_low)`` before the last two."""
    return COLUMNS[:-2] + low_rate_columns(fs_low) + COLUMNS[-2:]


def small_models(data, out) -> Path:
    """10 + 10 trees of depth 4 (the export's default size point) on four BROAD trials, no CV, small
    gain grids: a model directory whose learned filters run their trees in the loop."""
    cfg = load_config()
    cfg["classifier"].update(n_estimators=10, max_depth=4)
    cfg["regressor"].update(n_estimators=10, max_depth=4)
    cfg["gains"].update(tau=[17.5, 1.748], output_tau=[0.0], bias_tau=[-1.0, 3.498], mag_disturbance_scale=[0.0],
                        sweeps=1)
    cfg["gains"]["vqf"].update(tau_acc=[1.0, 3.0], confidence_floor=[0.0], sweeps=1)
    run_training(cfg, data_dir=data, trials=TRAIN_TRIALS, out=out, cv=False, verbose=False)
    return Path(out)


def filter_specs(models, learning_on_file=None):
    """``[(label, export(out_dir, fs) -> None, CSourceSet, includes, use_mag, host(out_dir, g, a, m, fs) -> quat)]``;
    ``learning_on_file``: the shipped models with learning on (``bench_learned_vqf.learning_on_model``), or None."""
    def vqf_core(use_mag):
        return (lambda d, fs: cvqf.export_c_vqf(d, fs, use_mag=use_mag, sizes=False), cvqf.C_VQF,
                ("tcf_vqf_config.h",), use_mag,
                lambda d, g, a, m, fs: cvqf.run_vqf_harness(cvqf.build_vqf_harness(d), g, a, m, dt=1.0 / fs))

    def learned_vqf(source, layout="array"):
        return (lambda d, fs: cvqf_toggling.export_c_vqf_toggling(source, d, fs, True, sizes=False,
                                                                   forest_layout=layout),
                cvqf_toggling.C_VQFT, (), True,
                lambda d, g, a, m, fs: cvqf_toggling.run_vqft_harness(cvqf_toggling.build_vqft_harness(d), g, a, m))

    specs = [("VQF core 9D (tcf_vqf.c)", *vqf_core(True)), ("VQF core 6D (tcf_vqf.c)", *vqf_core(False)),
             ("learned VQF 9D, pretrained model", *learned_vqf(PRETRAINED_FILE))]
    if learning_on_file is not None:
        specs.append((f"learned VQF 9D, the pretrained model's trees, learning on ({LEARNING_ON})",
                      *learned_vqf(learning_on_file)))
    if models is not None:
        specs.append(("learned VQF 9D, trained model (trees in the loop)", *learned_vqf(models)))
        specs.append(("learned VQF 9D, trained model, trees in the complete layout",
                      *learned_vqf(models, "complete")))
        specs.append(("toggling CF 9D, trained model (trees in the loop)",
                      lambda d, fs: cfilter.export_c_filter(models, d, fs, True, riscv=False), cfilter.C_FILTER, (),
                      True, lambda d, g, a, m, fs: cfilter.run_harness(cfilter.build_harness(d), g, a, m)))
    return specs


def measure_row(spec, opt, tmp: Path, g, a, m, fs, clock_hz, low) -> dict:
    """One filter at one optimisation level: the table row (without ``ratio_to_vqf``); ``low``: the samples
    at the low rate and that rate, ``(g, a, m, fs)``, run by an export at that rate."""
    label, export, sources, includes, use_mag, host = spec
    out_dir = tmp / f"{len(list(tmp.iterdir()))}"
    export(out_dir, fs)
    mag = m if use_mag else None
    meas = cycles.measure_filter(out_dir, sources, g, a, mag, fs, opt=opt, includes=includes)
    if meas.unknown:
        print(f"{label} {opt}: instructions priced 1 cycle by default: {sorted(meas.unknown)}", file=sys.stderr)
    ref = host(out_dir, g, a, mag, fs)
    s = cycles.summarize(meas, clock_hz, rates=(285.7,))
    g_low, a_low, m_low, fs_low = low
    low_dir = tmp / f"{len(list(tmp.iterdir()))}"
    export(low_dir, fs_low)
    s_low = cycles.summarize(cycles.measure_filter(low_dir, sources, g_low, a_low, m_low if use_mag else None, fs_low,
                                                   opt=opt, includes=includes), clock_hz, rates=(fs_low,))
    cycles_low, load_low = low_rate_columns(fs_low)
    print(f"{label} {opt}: {s['cycles_mean']:.0f} cycles/sample mean, {s['cycles_max']} max", flush=True)
    angle = float(np.nanmax(np.degrees(quat.angle_between(meas.quat, ref))))
    return {"filter": label, "opt": opt, "samples": s["samples"], "instructions_mean": round(s["instructions_mean"]),
            "instructions_max": s["instructions_max"], "cycles_mean": round(s["cycles_mean"]),
            "cycles_max": s["cycles_max"],
            "cycles_range_mean": f"{s['cycles_low_mean']:.0f}-{s['cycles_high_mean']:.0f}",
            "cycles_range_max": f"{s['cycles_low_max']}-{s['cycles_high_max']}", "us_mean": f"{s['us_mean']:.1f}",
            "load_285.7_mean_pct": f"{100 * s['load_285.7_mean']:.2f}",
            "load_285.7_max_pct": f"{100 * s['load_285.7_max']:.2f}",
            cycles_low: round(s_low["cycles_mean"]), load_low: f"{100 * s_low[f'load_{fs_low:g}_mean']:.2f}",
            "max_angle_deg": f"{angle:.1e}",
            "cycles_mean_exact": s["cycles_mean"], "per_function": meas.per_function}


def where_cycles_go(row: dict, smallest: float = 0.02) -> str:
    """One note line: the shares of ``row``'s cycles by function (``Measurement.per_function``; code the
    compiler inlined counts as its caller's), those under ``smallest`` summed as "other"."""
    per = row["per_function"]
    total = sum(per.values())
    big = sorted(((v / total, k) for k, v in per.items() if v / total >= smallest), reverse=True)
    other = 1.0 - sum(f for f, _ in big)
    parts = [f"`{k}` {100 * f:.0f} %" for f, k in big] + [f"other {100 * other:.0f} %"]
    return (f"Where the cycles of *{row['filter']}* at {row['opt']} go, by function (inlined code counts as "
            f"its caller's; libm's functions as themselves): {', '.join(parts)}.")


def notes(t, n, start, clock_mhz, models, args) -> list:
    """The table's note: the method, its assumptions, the samples and the model directory."""
    model = ("" if models is None else f" The trained rows use the model directory `{models}`." if args.models
             else f" The trained rows use a model directory trained here on BROAD trials {TRAIN_TRIALS} (10 + 10 "
             "trees of depth 4, the export's default size point; small gain grids).")
    return [f"An estimate, not a measurement on the hardware: the exported C compiled with arm-none-eabi-gcc for the "
            "Cortex-M4F (-mcpu=cortex-m4 -mthumb -mfpu=fpv4-sp-d16 -mfloat-abi=hard, newlib-nano libm), run in an "
            "instruction-set emulator (unicorn) one update per sample; the instruction counts are exact for that "
            "build, the cycles priced per instruction with the Cortex-M4 TRM's timings: "
            f"{cycles.CycleModel().describe()}. cycles_range: the taken branches priced with P = 1 and P = 3. "
            f"Samples {start}-{start + n - 1} of BROAD trial {t.name} at {t.fs:.1f} Hz; mean and max over them (with "
            "models in the loop the max is a sample where the trees run: every hop once the first window is "
            f"full). us_mean and load_285.7: at a {clock_mhz:g} MHz core clock, the share of a 285.7 Hz sample period "
            f"one update takes. cycles_mean_{t.fs / LOW_RATE_FACTOR:.1f} and load_{t.fs / LOW_RATE_FACTOR:.1f}: the "
            f"same samples every {LOW_RATE_FACTOR} averaged ({n // LOW_RATE_FACTOR} samples), the filter exported at "
            f"that rate: its mean cycles a sample there (a window end every 0.1 s, so every "
            f"{round(0.1 * t.fs / LOW_RATE_FACTOR)} samples) and their share of that period. ratio_to_vqf: "
            "cycles_mean ÷ the VQF core 9D's at "
            "the same -O level. max_angle_deg: the emulated build against the host build of the same export on "
            f"the same samples.{model}" + (" (quick mode: mini data, not a measurement to quote)" if args.quick
                                           else "")]


def main(argv=None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_common_args(p, NAME)
    p.add_argument("--models", default=None, help="trained model directory for the trees-in-the-loop rows (full "
                   "mode default: a small one trained first; --quick: none)")
    p.add_argument("--trial", default=None, help=f"trial (default {DEFAULT_TRIAL}; --quick: {QUICK_TRIAL})")
    p.add_argument("--samples", type=int, default=None, help="samples per filter (default 2000; --quick: 200)")
    p.add_argument("--start", type=int, default=0, help="first sample of the trial (default 0)")
    p.add_argument("--opt", nargs="+", default=None, help="gcc optimisation levels (default -O2 -Os; --quick: -O2)")
    p.add_argument("--clock-mhz", type=float, default=168.0, help="core clock for µs and load (default 168)")
    args = p.parse_args(argv)
    reason = cycles.missing_reason()
    if reason:
        p.error(f"the cycle estimate cannot run: {reason}")
    data = resolve_data_dir(data_dir(args))
    index = DatasetIndex.from_dir(data)
    t = index.load(index.select(args.trial or (QUICK_TRIAL if args.quick and not args.data else DEFAULT_TRIAL))[0])
    n = min(args.samples or (200 if args.quick else 2000), t.n_samples - args.start)
    opts = args.opt or (["-O2"] if args.quick else ["-O2", "-Os"])
    g, a, m = (x[args.start:args.start + n] for x in (t.gyr, t.acc, t.mag))
    first, n_low = args.start // LOW_RATE_FACTOR, n // LOW_RATE_FACTOR
    decimated = decimate_trial(t, LOW_RATE_FACTOR)  # block means, as the study's rate check
    low = (*(decimated[k][first:first + n_low] for k in ("imu_gyr", "imu_acc", "imu_mag")), t.fs / LOW_RATE_FACTOR)
    rows, ratios = [], {}
    with tempfile.TemporaryDirectory() as tmp:
        models = args.models or (None if args.quick else str(small_models(data, Path(tmp) / "models")))
        on_file = None if args.quick else learning_on_model(Path(tmp) / "learning_on.npz")
        work = Path(tmp) / "exports"
        work.mkdir()
        specs = filter_specs(models, on_file)
        for opt in opts:
            block = [measure_row(spec, opt, work, g, a, m, t.fs, 1e6 * args.clock_mhz, low) for spec in specs]
            vqf_cycles = block[0]["cycles_mean_exact"]  # the VQF core 9D, first of filter_specs
            for r in block:
                key = f"{r['filter']} {opt}"
                ratios[key] = r.pop("cycles_mean_exact") / vqf_cycles
                r["ratio_to_vqf"] = f"{ratios[key]:.2f}"
            rows += block
        # the most learned row of the first -O level: the shipped-size trees with learning on, else the last
        profiled = next((r for r in rows if "learning on" in r["filter"]), rows[len(specs) - 1])
        where = where_cycles_go(profiled)
        print(where)
        for r in rows:
            del r["per_function"]
        return finish(NAME, args, rows, table_columns(low[3]), "Cycles per sample of the C filters on a Cortex-M4F (estimate)",
                      [*notes(t, n, args.start, args.clock_mhz, models, args), where], digits=4, ratios=ratios)


if __name__ == "__main__":
    main()
