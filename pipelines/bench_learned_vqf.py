"""Speed of the pretrained learned VQF (``togglecf.LearnedVQF``) against the VQF core and VQF's C++,
measured in the same run on the same trial (9D; best of --repeats, interleaved, after a warm-up).

    python pipelines/bench_learned_vqf.py [--quick] [--trial 05] [--repeats 15] [--no-c] [--data DIR] [--out PATH]

Rows, each as µs per sample and as a ratio to ``vqf.VQF.updateBatch`` (C++):

* ``LearnedVQF`` with the shipped models and learning off (``learning_off``: VQF's settings, the core
  alone) and ``vqf_core`` (numba) with the same core settings: their ratio is the goal "within 5 % of
  the core's time";
* ``LearnedVQF`` as it ships (``LearnedVQF(rate)``: the shipped settings, the models in the loop where they
  learn something);
* the learned VQF with the shipped models in the loop (``ModelVQFTogglingFilter``), with VQF's settings
  (every tree walked, nothing learned) and with learning on: τ_acc per state ``LEARNED_TAU_ACC`` (the trees
  of the class probabilities walked every hop), and that plus the heading back-off σ_m ``LEARNED_SIGMA_M`` µT
  (the η̂_m trees walked too). Goal: at most 1.2× VQF's C++ for the τ_acc row (the goal line also gives its
  ratio round by round, each round's VQF timed beside it: the spread a shared machine puts on the ratio of
  the best times) and for the shipped one;
* without ``--no-c`` and with gcc: the C export (``cvqf_toggling``, float32, the harness's own
  per-sample timing of ``tcf_vqft_update``, -O2) of the learning-on settings, its trees in the array
  layout (the default, the faster on a microcontroller: ``bench_cycles.py``) and in the complete one
  (``--forest-layout complete``, the faster on a processor that predicts branches), and of the shipped
  ones, timed after the Python rows (not interleaved with them: a subprocess); ratio to VQF's C++
  timed between the C runs (its own row: a machine's speed can change between the two phases);
* where the learning-on row's time goes: the models alone (features pushed every sample, trees walked
  every hop, no filter) and the filter step alone driven by that row's predictions (steps 1-5:
  the followed modulation, the core);
* the same trial at a phone's rate, every ``LOW_RATE_FACTOR`` samples averaged (``run.transfer.decimate_trial``:
  95.2 Hz for BROAD's 285.7 Hz), interleaved with the rows above: VQF, the core, ``LearnedVQF`` as shipped and
  the τ_acc row, each against VQF at that rate, with the same goals. The models predict every 0.1 s at any rate
  (their window and hop are in seconds), so a sample at a lower rate carries more of their cost.

The outputs are checked too: ``LearnedVQF`` learning off against ``vqf_core`` (largest quaternion
component difference: 0 when it runs the core alone). ``--quick``: the mini trial 24 (4000
samples), 2 repeats; the test suite runs it for the table's shape, never its timings.
"""
from __future__ import annotations

import argparse
import dataclasses
import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from numba import njit
from bench_common import add_common_args, context_note, data_dir, finish, interleaved_times, round_ratios, vqf_batch

from togglecf.data.broad import DatasetIndex, resolve_data_dir
from togglecf.embedded import cvqf_toggling as cv
from togglecf.features.streaming import push_sample
from togglecf.filters.vqf_core import VQFCoreFilter
from togglecf.filters.vqf_toggling import VQFTogglingFilter
from togglecf.learn.portable import save_portable
from togglecf.run.transfer import decimate_trial
from togglecf.toggling.gains import mode_name
from togglecf.toggling.inloop import ModelVQFTogglingFilter, hop_predict
from togglecf.toggling.pretrained import PRETRAINED_FILE, LearnedVQF, load_pretrained, pretrained_settings

NAME = "bench_learned_vqf"
QUICK_TRIAL = "24"
#: τ_acc [s] per motion state of the learning-on rows (the first state's, then geometric up to the last)
LEARNED_TAU_ACC = (1.5, 6.0)
#: σ_m [µT] of the learning-on row with the heading back-off
LEARNED_SIGMA_M = 10.0
VQF = "vqf (VQF.updateBatch, C++)"
CORE = "vqf_core (numba), the core settings"
OFF = "LearnedVQF, the shipped models with learning off (VQF's settings: the core alone)"
SHIPPED = "LearnedVQF as shipped (its learned settings)"
LOOP_OFF = "models in the loop, VQF's settings (all trees' work, nothing learned)"
LOOP_TAU = "models in the loop, learning on: τ_acc per state"
LOOP_MAG = "models in the loop, learning on: τ_acc per state + heading back-off"
PART_MODELS = "part of the learning-on row: the models alone (features every sample, trees every hop)"
PART_STEP = "part of the learning-on row: the filter step alone (predictions given, its own batch loop)"
PREDS = "predictions of the learning-on row"
C_TAU = "C export (float32), learning on: τ_acc per state"
C_TAU_COMPLETE = "C export (float32), learning on: τ_acc per state, trees in the complete layout"
C_SHIPPED = "C export (float32), as shipped"
VQF_C = "vqf (VQF.updateBatch, C++), timed between the C rows: their reference"
#: the phone-rate rows: the trial every LOW_RATE_FACTOR samples averaged
LOW_RATE_FACTOR = 3
LOW_RATE = f", at a phone's rate (every {LOW_RATE_FACTOR} samples averaged)"
LOW_VQF, LOW_CORE, LOW_SHIPPED, LOW_TAU = VQF + LOW_RATE, CORE + LOW_RATE, SHIPPED + LOW_RATE, LOOP_TAU + LOW_RATE


def learning_off(settings):
    """``settings`` with nothing learned (``VQFTogglingSettings.learning_off``): every per-state value the core's,
    no back-off, no noise weight."""
    off = dataclasses.replace(settings, tau_acc_states=(), tau_mag_states=(), bias_sigma_motion_states=(),
                              rest_th_gyr_states=(), rest_th_acc_states=(), mag_disturbance_scale=0.0,
                              field_change_scale=0.0, noise_weight_acc=0.0, noise_weight_mag=0.0)
    assert off.learning_off(True), off
    return off


def learning_on(settings, backoff: bool):
    """``learning_off(settings)`` with τ_acc per state (``LEARNED_TAU_ACC``) and, with ``backoff``, σ_m
    ``LEARNED_SIGMA_M``."""
    tau = tuple(np.geomspace(*LEARNED_TAU_ACC, len(settings.states)))
    return dataclasses.replace(learning_off(settings), tau_acc_states=tau,
                               mag_disturbance_scale=LEARNED_SIGMA_M if backoff else 0.0)


@njit
def models_alone(window, models, held, gyr, acc, mag):
    """The in-loop models without a filter (``toggling.inloop.run_inloop``'s part before the step):
    features pushed every sample, the trees walked at every window end."""
    L, hop = window.ring.shape[0], window.hop
    done = int(window.aux[0])
    for i in range(gyr.shape[0]):
        push_sample(window.ring, window.aux, window.params, window.last_src, (gyr[i, 0], gyr[i, 1], gyr[i, 2]),
                    (acc[i, 0], acc[i, 1], acc[i, 2]), (mag[i, 0], mag[i, 1], mag[i, 2]))
        k = done + i + 1
        if k >= L and (k - L) % hop == 0:
            hop_predict(window, models, held)


def part_runs(t, gyr, acc, mag, outs) -> dict:
    """Where the time of the learning-on row goes: the models alone (``models_alone``), and the filter step
    alone driven by the predictions the models made in that row (``VQFTogglingFilter``, given predictions)."""
    pm = load_pretrained()
    on = learning_on(pretrained_settings(True), False)
    models = ModelVQFTogglingFilter(t.fs, on, models=pm.models).predictor
    step = VQFTogglingFilter(t.fs, on)

    def run_models():
        models.reset()
        models_alone(models.window, models.arrays, models.held, gyr, acc, mag)

    def run_step():
        step.reset()
        step.update_batch(gyr, acc, mag, predictions=outs[PREDS])
    return {PART_MODELS: run_models, PART_STEP: run_step}


def all_trees(f):
    """``f`` walking every tree of its models, also those of outputs its settings never use: what the models
    cost in the loop."""
    f.forest = f.models.forest
    return f


def python_runs(t, gyr, acc, mag, tmp: Path) -> tuple[dict, dict, dict]:
    """The Python rows' callables (each from a fresh state), the outputs they write and their filters
    (``tmp``: a directory for the learning-off model file)."""
    pm, shipped = load_pretrained(), pretrained_settings(True)
    outs = {}
    off_file = portable_with(tmp / "learning_off.npz", learning_off(shipped), "learning off")
    filters = {OFF: LearnedVQF(t.fs, model=off_file), CORE: VQFCoreFilter(t.fs, shipped.core_settings),
               SHIPPED: LearnedVQF(t.fs),
               LOOP_OFF: all_trees(ModelVQFTogglingFilter(t.fs, learning_off(shipped), models=pm.models)),
               LOOP_TAU: ModelVQFTogglingFilter(t.fs, learning_on(shipped, False), models=pm.models),
               LOOP_MAG: ModelVQFTogglingFilter(t.fs, learning_on(shipped, True), models=pm.models)}

    def run(key, f):
        def go():  # the filter alone: whatever is derived from its output is derived outside the timing
            f.reset()
            outs[key] = f.update_batch(gyr, acc, mag)
        return go

    return {k: run(k, f) for k, f in filters.items()}, outs, filters


def low_rate_runs(t) -> tuple[float, int, dict]:
    """The phone-rate rows' callables: VQF, the core, ``LearnedVQF`` as shipped and the τ_acc row on trial ``t``
    every ``LOW_RATE_FACTOR`` samples averaged. Returns (that rate [Hz], its number of samples, {row: callable})."""
    arrays = decimate_trial(t, LOW_RATE_FACTOR)
    fs = t.fs / LOW_RATE_FACTOR
    gyr, acc, mag = (np.ascontiguousarray(arrays[k], np.float64) for k in ("imu_gyr", "imu_acc", "imu_mag"))
    pm, shipped = load_pretrained(), pretrained_settings(True)
    filters = {LOW_CORE: VQFCoreFilter(fs, shipped.core_settings), LOW_SHIPPED: LearnedVQF(fs),
               LOW_TAU: ModelVQFTogglingFilter(fs, learning_on(shipped, False), models=pm.models)}

    def run(f):
        def go():
            f.reset()
            f.update_batch(gyr, acc, mag)
        return go
    return fs, len(gyr), {LOW_VQF: vqf_batch(fs, gyr, acc, mag), **{k: run(f) for k, f in filters.items()}}


def prediction_rows(f, out) -> np.ndarray:
    """The prediction rows ``(N, S + 6)`` the in-loop filter ``f`` held, from its output's diagnostics."""
    return np.stack([out.diagnostics[k] for k in f.layout.names(f.models.class_names)], axis=1)


def portable_with(path: Path, settings, what: str) -> Path:
    """The shipped models with the 9D ``settings`` as a portable model file at ``path``."""
    pm = load_pretrained()
    gains = {**pm.gains, mode_name("vqf_toggling", True): dataclasses.asdict(settings)}
    return save_portable(path, pm.models, gains, {"note": f"bench_learned_vqf: {what}"})


def learning_on_model(path: Path) -> Path:
    """The shipped models with the learning-on settings (``learning_on``, 9D) as a portable model file at
    ``path``: what ``export_c_vqf_toggling`` exports with the trees in the loop (also ``bench_cycles.py``)."""
    return portable_with(path, learning_on(pretrained_settings(True), False), "learning on")


def c_harnesses(tmp: Path, fs: float) -> dict:
    """Row name -> compiled harness of the C export (learning on, shipped); {} without gcc."""
    if shutil.which("gcc") is None:
        return {}
    on_file = learning_on_model(tmp / "learning_on.npz")
    out = {}
    for i, (key, path, layout) in enumerate(((C_TAU, on_file, "array"), (C_TAU_COMPLETE, on_file, "complete"),
                                             (C_SHIPPED, PRETRAINED_FILE, "array"))):
        d = tmp / f"export_{i}"
        cv.export_c_vqf_toggling(path, d, fs=fs, sizes=False, forest_layout=layout)
        out[key] = cv.build_vqft_harness(d)
    return out


def c_us(exes: dict, t, gyr, acc, mag, repeats: int) -> dict:
    """Best per-sample time [µs] of each harness's ``tcf_vqft_update`` loop over ``repeats`` runs, and
    (key ``VQF``) of ``vqf.VQF.updateBatch`` timed between them: the C rows' own reference (a
    subprocess's timing, so not interleaved with the Python rows)."""
    best = {}
    vqf = vqf_batch(t.fs, gyr, acc, mag)
    for _ in range(repeats):
        t0 = time.perf_counter()
        vqf()
        best[VQF] = min(best.get(VQF, np.inf), 1e6 * (time.perf_counter() - t0) / len(gyr))
        for key, exe in exes.items():
            _, diag = cv.run_vqft_harness(exe, gyr, acc, mag, diagnostics=True, fs=t.fs)
            best[key] = min(best.get(key, np.inf), diag["ns_per_sample"] / 1e3)
    return best


def main(argv=None) -> dict:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_common_args(p, NAME)
    p.add_argument("--trial", default=None, help=f"default 05; --quick {QUICK_TRIAL}")
    p.add_argument("--repeats", type=int, default=None, help="default 15; --quick 2")
    p.add_argument("--no-c", action="store_true", help="leave out the C export rows")
    args = p.parse_args(argv)
    if not PRETRAINED_FILE.is_file():
        sys.exit(f"{PRETRAINED_FILE}: this checkout ships no pretrained model")
    index = DatasetIndex.from_dir(resolve_data_dir(data_dir(args)))
    t = index.load(index.select(args.trial or (QUICK_TRIAL if args.quick else "05"))[0])
    repeats = args.repeats or (2 if args.quick else 15)
    gyr, acc, mag = (np.ascontiguousarray(x, np.float64) for x in (t.gyr, t.acc, t.mag))
    n = t.n_samples
    with tempfile.TemporaryDirectory() as tmp:
        runs, outs, filters = python_runs(t, gyr, acc, mag, Path(tmp))
        runs[LOOP_TAU]()
        outs[PREDS] = prediction_rows(filters[LOOP_TAU], outs[LOOP_TAU])  # they drive PART_STEP
        low_fs, n_low, low = low_rate_runs(t)
        runs = {VQF: vqf_batch(t.fs, gyr, acc, mag), **runs, **part_runs(t, gyr, acc, mag, outs), **low}
        exes = {} if args.no_c else c_harnesses(Path(tmp), t.fs)
        times = interleaved_times(runs, repeats)
        us = {k: 1e6 * min(v) / (n_low if k in low else n) for k, v in times.items()}
        us_c = c_us(exes, t, gyr, acc, mag, repeats) if exes else {}
    ref, ref_c = us[VQF], us_c.pop(VQF, None)
    ratios = {k: v / (us[LOW_VQF] if k in low else ref) for k, v in us.items()}
    ratios.update({k: v / ref_c for k, v in us_c.items()})
    ratios["LearnedVQF / vqf_core"] = us[OFF] / us[CORE]
    diff = float(np.abs(outs[OFF].quat - outs[CORE].quat).max())
    rows = [{"filter": k, "us_per_sample": v, "ratio_to_vqf": ratios[k],
             "ratio_to_core": v / us[LOW_CORE if k in low else CORE]} for k, v in us.items()]
    if us_c:
        rows.append({"filter": VQF_C, "us_per_sample": ref_c, "ratio_to_vqf": 1.0, "ratio_to_core": None})
    rows += [{"filter": k, "us_per_sample": v, "ratio_to_vqf": ratios[k], "ratio_to_core": None}
             for k, v in us_c.items()]
    shipped = filters[SHIPPED]
    as_shipped = ("it learns nothing, the core alone" if shipped.runs_core_alone else  # σ_m, τ_acc, trees walked
                  f"σ_m {shipped.settings.mag_disturbance_scale:g} µT, τ_acc per state "
                  f"{', '.join(f'{v:g}' for v in shipped.settings.tau_acc_states)} s: "
                  f"{len(shipped.runner.predictor.forest.roots)} trees walked")
    what = (f"Trial {t.name} ({n} samples at {t.fs:.1f} Hz), 9D, the shipped model "
            f"({len(load_pretrained().models.forest.roots)} trees; as shipped: {as_shipped}); learning on: τ_acc per "
            f"state {LEARNED_TAU_ACC[0]:g} to {LEARNED_TAU_ACC[1]:g} s (+ σ_m {LEARNED_SIGMA_M:g} µT for the "
            "back-off row); "
            f"best of {repeats} interleaved runs after a warm-up. LearnedVQF against vqf_core: largest quaternion "
            f"difference {diff:.2g}. C rows: the harness's own timing of its update loop (gcc -O2, float32, "
            "best of as many runs), after the Python rows, against VQF's C++ timed between them (the machine's "
            f"speed can change from one phase to the next). Rows at a phone's rate: the trial every "
            f"{LOW_RATE_FACTOR} samples averaged ({low_fs:.1f} Hz, {n_low} samples), ratios against VQF and the "
            "core at that rate")
    print(what)
    res = finish(NAME, args, rows, ["filter", "us_per_sample", "ratio_to_vqf", "ratio_to_core"],
                 "Learned VQF speed against the VQF core and VQF", [context_note(what, args)], ratios=ratios)
    off, loop = ratios["LearnedVQF / vqf_core"], ratios[LOOP_TAU]
    print(f"\ngoal: LearnedVQF learning off <= 1.05x vqf_core -> {off:.3f}x ({'met' if off <= 1.05 else 'NOT met'})")
    met = "met" if loop <= 1.2 else "NOT met"
    lo, mid, hi = round_ratios(times, LOOP_TAU, VQF)
    print(f"goal: learned VQF with models in the loop <= 1.2x VQF -> {loop:.2f}x ({met}; round by round, against "
          f"VQF timed beside it: {lo:.2f}x to {hi:.2f}x, median {mid:.2f}x)")
    shipped_ratio = ratios[SHIPPED]
    print(f"goal: LearnedVQF as shipped <= 1.2x VQF -> {shipped_ratio:.2f}x "
          f"({'met' if shipped_ratio <= 1.2 else 'NOT met'})")
    for key, label in ((LOW_SHIPPED, "LearnedVQF as shipped"), (LOW_TAU, "learned VQF with models in the loop")):
        lo, mid, hi = round_ratios(times, key, LOW_VQF)
        print(f"goal: {label} <= 1.2x VQF at {low_fs:.1f} Hz -> {ratios[key]:.2f}x "
              f"({'met' if ratios[key] <= 1.2 else 'NOT met'}; round by round {lo:.2f}x to {hi:.2f}x, median "
              f"{mid:.2f}x)")
    for key, layout in ((C_TAU, "array"), (C_TAU_COMPLETE, "complete")):
        if key in ratios:
            print(f"goal: its C export with models in the loop ({layout} layout) <= 1.2x VQF -> {ratios[key]:.2f}x "
                  f"({'met' if ratios[key] <= 1.2 else 'NOT met'})")
    res.update(max_quat_diff=diff)
    return res


if __name__ == "__main__":
    main()
