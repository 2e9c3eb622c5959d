"""The VQF core with learned time constants (``togglecf.toggling.inloop.ModelVQFTogglingFilter``)
as a self-contained C99 source set.

``export_c_vqf_toggling(model_dir, out_dir, fs=None, use_mag=True, max_fs=400)`` writes into ``out_dir`` a
rate-free filter: ``tcf_vqft_init(&f, fs)`` takes the rate (up to ``TCF_MAX_FS``) and derives every
per-sample coefficient and the features' window and hop from it and the settings in seconds;
``tcf_vqft_update_dt`` takes the per-sample Δt of the gyro integration:

* the shared C pieces, unchanged templates of ``togglecf/embedded/``: ``tcf_features.{h,c}``
  (the models in the loop: streaming features, the out-of-range check, the tree walk; the same
  file the toggling CF export ships) and ``tcf_vqf.{h,c}`` (the VQF core of ``export_c_vqf``;
  ``tcf_vqf_update_mod`` runs it with modulated coefficients);
* ``tcf_vqf_toggling.{h,c}``: steps 1-5 of ``filters.vqf_toggling`` (probabilities -> blended
  ln τ_acc, ln τ_mag, ln σ_motion with confidence λ -> coefficients, recomputed only when the
  probabilities change; noise removal; the core step), float32, no heap, one fixed-size
  ``tcf_vqft_t``;
* ``tcf_config.h`` (generated: ``TCF_LEARNING_OFF`` (1 where the mode's settings learn
  nothing: ``tcf_vqft_update`` runs the core alone, as ``LearnedVQF``), the feature settings in
  seconds, ``TCF_MAX_FS`` and the ring size ``TCF_WINDOW_MAX``, the harness's default rate
  ``TCF_DEFAULT_FS``, the out-of-range fallback's feature bounds, class names, the per-state
  values as natural logarithms ``TCF_VQFT_LN_*``, confidence floor, noise weights, model/gains
  hashes) and ``tcf_vqf_config.h`` (the core's
  settings of ``gains.json``, i.e. the fallback, as ``TCF_VQF_PARAMS_INIT``);
* ``tcf_forest.{h,c}``: the merged forest without the trees the filter never uses (η̂_a at
  w_a = 0, η̂_m in 6D or at w_m = 0), as ``ModelVQFTogglingFilter`` walks it;
* ``tcf_vqf_toggling_harness.c`` + ``tcf_csv.h`` + ``Makefile``: the host program, and
  ``vqf_toggling_report.json``: the returned report (state bytes, object sizes host / rv32imc /
  Cortex-M4F per source and for trees + filter, the same as a ``--gc-sections`` firmware link
  keeps it, stack of the ``tcf_vqft_update`` call chain, linked program sizes).

``build_vqft_harness(out_dir)`` compiles the harness; ``run_vqft_harness(exe, gyr, acc, mag)``
runs it on arrays (``predictions=``: drive steps 1-5 with given predictions instead of the trees).
"""
from __future__ import annotations

import shutil
from dataclasses import asdict
from pathlib import Path

from togglecf.core.io import atomic_write_json
from togglecf.embedded.cvqf import vqf_config_header, vqf_state_bytes
from togglecf.embedded import framework, learned
from togglecf.embedded.forest_export import c_layout_bytes
from togglecf.embedded.library import LibrarySpec, write_library
from togglecf.embedded.toolchain import (
    ARM_FLAGS,
    ARM_GCC,
    ARM_SIZE,
    RISCV_GCC,
    arm_available,
    c_float,
    link_arm,
    link_riscv,
    reachable_code_size,
    riscv_flags,
    run_prediction_harness,
    unit_chain_stack,
)

__all__ = ["export_c_vqf_toggling", "build_vqft_harness", "run_vqft_harness", "VQFT_TEMPLATES", "VQFT_SOURCES",
           "C_VQFT", "state_bytes_formula", "DIAG_NAMES"]

VQFT_TEMPLATES = ("tcf_vqf_toggling.h", "tcf_vqf_toggling.c", *learned.FEATURE_TEMPLATES, "tcf_vqf.h", "tcf_vqf.c",
                  "tcf_math.h", "tcf_vqf_toggling_harness.c", "tcf_csv.h")
#: the firmware sources: filter + trees (the object code of the 32 KB goal)
VQFT_SOURCES = ("tcf_vqf_toggling.c", "tcf_features.c", "tcf_vqf.c", "tcf_forest.c")
#: the learned VQF filter as C files (framework.CSourceSet)
C_VQFT = framework.CSourceSet(
    what="the exported learned VQF filter", exporter="export_c_vqf_toggling", api_header="tcf_vqf_toggling.h",
    state_type="tcf_vqft_t", sources=VQFT_SOURCES,
    headers=("tcf_vqf_toggling.h", *learned.FEATURE_HEADERS, "tcf_vqf.h", "tcf_math.h", "tcf_forest.h", "tcf_config.h",
             "tcf_vqf_config.h"),
    templates=VQFT_TEMPLATES, generated=("tcf_config.h", "tcf_vqf_config.h", "tcf_forest.h", "tcf_forest.c"),
    harness="tcf_vqf_toggling_harness",
    firmware=framework.FirmwareCalls(setup="if (tcf_vqft_init(&tcf_f, (float)TCF_DEFAULT_FS) != 0) return 1;",
                           update="tcf_vqft_update(&tcf_f, g, a, m);", quat="tcf_vqft_quat(&tcf_f, tcf_q);"),
    note="Never -ffast-math.")
#: columns of ``--diag`` after the predictions
DIAG_NAMES = ("tau_acc", "tau_mag", "trust", "fallback", "rest", "mag_dist")


def state_bytes_formula(window_max: int, n_classes: int) -> int:
    """``sizeof(tcf_vqft_t)`` as documented in ``tcf_vqf_toggling.h``: the core's
    ``TCF_VQF_STATE_BYTES`` (``cvqf.vqf_state_bytes``), the features ``4 · (43 + 12 L_max + S)``
    (ring 12 L_max, ``TCF_WINDOW_MAX`` rows for ``TCF_MAX_FS``; per-sample constants of the init
    rate 6, EMA references 10, candidate field 5, previous acc 3, last-sample features 10,
    counters 3, η̂ 6; class probabilities S) and ``4 · (29 + S)`` (modulation 7, diagnostics 3, the
    last prediction S + 6, the followed modulation and back-off 6, its gain 1, the field change 5 and
    its gain 1)."""
    return vqf_state_bytes() + 4 * (43 + 12 * int(window_max) + int(n_classes)) + 4 * (29 + int(n_classes))


def _filter_defines(filt) -> str:
    """The learned VQF filter's own lines of ``tcf_config.h``: ``TCF_LEARNING_OFF`` (1: the settings
    learn nothing in this mode, ``VQFTogglingSettings.learning_off``; the update runs the core alone),
    the per-state values as natural logarithms, the core's ones (the fallback), back-off, confidence
    floor, noise weights and the followed modulation."""
    s, p = filt.settings, filt.params
    return f"""/* learning off (VQFTogglingSettings.learning_off: every learned value of this mode equals the core's):
 * 1: tcf_vqft_update runs the VQF core alone, no features pushed, no trees walked (as LearnedVQF) */
#define TCF_LEARNING_OFF {1 if s.learning_off(filt.use_mag) else 0}
/* learned time constants (filters.vqf_toggling, steps 1-3), per class in the order above, as
 * natural logarithms (the blend is in ln tau): tau_acc [s] {', '.join(f'{t:g}' for t in s.tau_acc_states)};
 * tau_mag [s] {', '.join(f'{t:g}' for t in s.tau_mag_states)}; sigma_motion [deg/s] {', '.join(f'{t:g}' for t in s.bias_sigma_motion_states)}
 * (ln of rad/s). The core's own values (the fallback: no prediction, or low confidence):
 * tau_acc {s.tau_acc:g} s, tau_mag {s.tau_mag:g} s, sigma_motion {s.bias_sigma_motion:g} deg/s. */
#define TCF_VQFT_LN_TAU_ACC_INIT {framework.c_float_array(p.ln_tau_acc)}
#define TCF_VQFT_LN_TAU_MAG_INIT {framework.c_float_array(p.ln_tau_mag)}
#define TCF_VQFT_LN_SIGMA_MOTION_INIT {framework.c_float_array(p.ln_sigma_motion)}
#define TCF_VQFT_LN_TAU_ACC_CORE {c_float(p.ln_tau_acc_core)}
#define TCF_VQFT_LN_TAU_MAG_CORE {c_float(p.ln_tau_mag_core)}
#define TCF_VQFT_LN_SIGMA_MOTION_CORE {c_float(p.ln_sigma_motion_core)}
/* rest thresholds per class, as natural logarithms: th_omega [deg/s] {', '.join(f'{t:g}' for t in s.rest_th_gyr_states)}
 * (ln of rad/s), th_a [m/s^2] {', '.join(f'{t:g}' for t in s.rest_th_acc_states)}; the core's: {s.rest_th_gyr:g} deg/s, {s.rest_th_acc:g} m/s^2 */
#define TCF_VQFT_LN_REST_TH_GYR_INIT {framework.c_float_array(p.ln_rest_th_gyr)}
#define TCF_VQFT_LN_REST_TH_ACC_INIT {framework.c_float_array(p.ln_rest_th_acc)}
#define TCF_VQFT_LN_REST_TH_GYR_CORE {c_float(p.ln_rest_th_gyr_core)}
#define TCF_VQFT_LN_REST_TH_ACC_CORE {c_float(p.ln_rest_th_acc_core)}
/* sigma_m [uT] of step 3 (heading gain / (1 + min((|eta_m| / sigma_m)^2, mag_rejection_factor - 1)));
   0: off (always 0 in 6D) */
#define TCF_VQFT_MAG_DISTURBANCE_SCALE {c_float(p.mag_disturbance_scale)}
/* mag_backoff_measured: the back-off acts on at most the disturbance the magnetometer shows (instead of
   the rejection-factor bound) */
#define TCF_VQFT_MAG_BACKOFF_MEASURED {1 if s.mag_backoff_measured else 0}
/* sigma_f [uT] of step 3b (the back-off on the field's change in the 6D earth frame; 0: off, always 0 in
   6D) and the time constant [s] of the low-pass it is compared with */
#define TCF_VQFT_FIELD_CHANGE_SCALE {c_float(p.field_change_scale)}
#define TCF_VQFT_FIELD_CHANGE_TAU {c_float(p.field_change_tau)}
#define TCF_VQFT_CONFIDENCE_FLOOR {c_float(s.confidence_floor)}   /* c0 of step 1 */
#define TCF_VQFT_NOISE_WEIGHT_ACC {c_float(s.noise_weight_acc)}   /* w_a of step 4 */
#define TCF_VQFT_NOISE_WEIGHT_MAG {c_float(s.noise_weight_mag)}   /* w_m of step 4 */
#define TCF_VQFT_NOISE_ACC {1 if s.noise_weight_acc != 0 else 0}   /* 0: w_a = 0, step 4 leaves acc as is (a - 0 eta = a) */
#define TCF_VQFT_NOISE_MAG {1 if s.noise_weight_mag != 0 else 0}   /* 0: w_m = 0, step 4 leaves mag as is */
/* modulation_tau [s]: ln tau_acc, ln tau_mag follow the blended values with the per-sample gain
 * 1 - exp(-Ts / modulation_tau) at the init rate; TCF_VQFT_FOLLOW 0: at once (modulation_tau 0) */
#define TCF_VQFT_FOLLOW {1 if s.modulation_tau > 0.0 else 0}
#define TCF_VQFT_MODULATION_TAU {c_float(s.modulation_tau)}
"""


#: the API a firmware calls (as ``C_VQFT.firmware``): the roots of ``code_bytes_gc``
_FIRMWARE_ROOTS = ("tcf_vqft_update", "tcf_vqft_init", "tcf_vqft_quat")


def _reachable_code(srcs, out_dir: Path) -> dict:
    """text + data of trees + filter as a ``--gc-sections`` firmware link keeps them when it calls
    ``_FIRMWARE_ROOTS`` (toolchain.reachable_code_size; unused API dropped, libm not counted), per
    target (None without the compiler). Reported beside ``code_bytes``, which counts whole objects."""
    rv = riscv_flags()
    targets = {"host": ("gcc", [], "size"),
               "riscv": None if rv is None else (RISCV_GCC, rv, "riscv64-unknown-elf-size"
                                                 if shutil.which("riscv64-unknown-elf-size") else "size"),
               "arm": (ARM_GCC, list(ARM_FLAGS), ARM_SIZE if shutil.which(ARM_SIZE) else "size")
               if arm_available() else None}
    out = {}
    for t, spec in targets.items():
        if spec is None:
            out[t] = None
            continue
        m = reachable_code_size(*spec, srcs, [out_dir], _FIRMWARE_ROOTS)
        out[t] = m["text"] + m["data"]
    return out


def _stack(out_dir: Path) -> dict:
    """Deepest stack of the ``tcf_vqft_update`` call chain over all four sources (one
    translation unit; libm not counted), rv32imc and Cortex-M4F (None without the compiler)."""
    return unit_chain_stack([out_dir / s for s in VQFT_SOURCES], [out_dir], "tcf_vqft_update")


def export_c_vqf_toggling(model_dir, out_dir, fs=None, use_mag: bool = True, *, sizes: bool = True,
                          max_fs: float = learned.DEFAULT_MAX_FS, forest_layout: str = "array") -> dict:
    """Write the learned VQF filter of ``model_dir`` (a ``togglecf train`` directory whose
    ``gains.json`` has ``vqf_9d`` / ``vqf_6d``, or a portable model file: the pretrained model's
    ``learned_vqf.npz``, ``learned.load_portable_export``) into ``out_dir``, rate-free: the C takes its rate
    at init (``tcf_vqft_init(&f, fs)``, any rate up to ``max_fs`` [Hz], ``TCF_MAX_FS``, for which
    the feature ring is sized). ``fs`` [Hz]: only the default rate of the host harness and the
    size probes (``TCF_DEFAULT_FS``; None: the models' ``sampling_rate``). ``forest_layout``: the trees'
    C layout (``forest_export.forest_to_c``: ``array``, the faster on a microcontroller, or ``complete``,
    the faster on a processor that predicts branches). Returns the report
    (also ``out_dir/vqf_toggling_report.json``): ``files``, ``state_bytes`` (sizeof(tcf_vqft_t), gcc),
    ``fallback`` (the out-of-range rule as exported) and, with ``sizes``, ``object_sizes``
    {source: {host, riscv, arm}} (-Os; None where a cross compiler is missing), ``code_bytes``
    {host, riscv, arm}: text + data of the four objects of trees + filter (the measure of the
    32 KB goal), ``code_bytes_trees`` (tcf_forest.c alone), ``code_bytes_gc``: the same four
    compiled with ``-ffunction-sections`` and kept by ``--gc-sections`` from
    ``tcf_vqft_init`` / ``tcf_vqft_update`` / ``tcf_vqft_quat`` (the unused API dropped; libm and
    soft-float still not counted), ``stack`` {riscv, arm} of the ``tcf_vqft_update`` chain,
    ``linked_riscv`` / ``linked_arm`` program sizes (with libm, soft-float and start-up);
    ``library``: the Arduino / PlatformIO library written beside (``out_dir/arduino/TogglecfLearnedVQF``,
    ``library.write_library``; its sketch set to ``fs``)."""
    model_dir, out_dir = Path(model_dir), Path(out_dir)
    if model_dir.is_file():  # a portable model file (learn.portable), e.g. the pretrained model
        ex = learned.load_portable_export(model_dir, fs, use_mag, max_fs=max_fs)
    else:
        ex = learned.load_model_export(model_dir, fs, use_mag, kind="vqf_toggling", max_fs=max_fs)
    filt, s, L, k = ex.filt, ex.filt.settings, ex.window_max, len(ex.classes)
    comment, common = learned.learned_config(ex, model_dir, use_mag, "filter: VQF core with learned time constants "
                                             f"({'model file' if model_dir.is_file() else 'gains.json'}, "
                                             f"{'vqf_9d' if use_mag else 'vqf_6d'})")
    rate = (f"/* the rate is set at init, tcf_vqft_init(&f, fs); the host harness's and the size probes' default */\n"
            f"#define TCF_DEFAULT_FS {c_float(ex.fs)}   /* Hz */\n")
    config = framework.config_header("tcf_config.h", "cvqf_toggling.export_c_vqf_toggling", comment,
                                     rate + common + "\n" + _filter_defines(filt))
    files = framework.write_source_set(out_dir, C_VQFT, {
        "tcf_config.h": config, "tcf_vqf_config.h": vqf_config_header(None, s.core_settings, use_mag)})
    forest_files, n_nodes = learned.write_forest(out_dir, model_dir, ex, forest_layout)
    files += forest_files

    report = {"out_dir": str(out_dir), "model_dir": str(model_dir), "files": [str(p) for p in files], "fs": ex.fs,
              "rate": "at init (tcf_vqft_init); fs: the harness's default", "max_fs": ex.max_fs,
              "window_max": L, "use_mag": bool(use_mag), "window": ex.window, "hop": ex.hop, "n_classes": k,
              "class_names": ex.classes,
              "n_features": int(ex.forest.n_features), "n_trees": int(len(ex.forest.roots)), "n_nodes": n_nodes,
              "forest_layout": forest_layout,
              "forest_layout_bytes": c_layout_bytes(ex.forest),
              "dropped_outputs": ex.dropped, "settings": asdict(s), "fallback": learned.fallback_config(filt.models)[1],
              "schema_hash": ex.schema_hash, "model_hash": ex.model_hash, "gains_sha256": ex.gains_hash,
              "coefficients": "core: derived in C by tcf_vqf_init; modulation: tcf_vqf_mod_from at each "
                              "probability change (float32)"}
    size, documented, feat_size, core_size = framework.probe_sizes(
        out_dir, "tcf_vqf_toggling.h",
        ["sizeof(tcf_vqft_t)", "TCF_VQFT_STATE_BYTES", "sizeof(tcf_features_t)", "sizeof(tcf_vqf_t)"])
    if not size == documented == state_bytes_formula(L, k):
        raise AssertionError(f"sizeof(tcf_vqft_t) {size}, TCF_VQFT_STATE_BYTES {documented} and "
                             f"state_bytes_formula {state_bytes_formula(L, k)} disagree")
    report["state_bytes"] = size
    report["state_bytes_parts"] = {"core": core_size, "features": feat_size, "learned": size - core_size - feat_size}
    if sizes:
        report.update(_code_sizes(out_dir))
    report["library"] = str(write_library(out_dir, library_spec(report), ex.fs))
    atomic_write_json(out_dir / "vqf_toggling_report.json", report)
    return report


#: the firmware files of the export that the Arduino / PlatformIO library ships in src/
LIBRARY_FILES = (*VQFT_SOURCES, *C_VQFT.headers)


def _size_line(report: dict) -> str:
    """The README's code-size sentence from the report's sizes (when measured)."""
    gc = report.get("code_bytes_gc") or {}
    got = [f"{v / 1024:.1f} KiB {t}" for t, v in (("Cortex-M4F", gc.get("arm")), ("rv32imc", gc.get("riscv")))
           if v is not None]
    return (f" Code (trees + filter as a `--gc-sections` link keeps them, -Os, libm not counted): {', '.join(got)}."
            if got else "")


def library_spec(report: dict) -> LibrarySpec:
    """The Arduino / PlatformIO library of a learned VQF export (``report``: the export's report):
    its metadata, the sketch's calls and a README with rate, units, frames and memory."""
    mode = "9D (gyr + acc + mag)" if report["use_mag"] else "6D (gyr + acc)"
    readme = f"""The learned VQF of [togglecf](https://pypi.org/project/togglecf/): the VQF orientation filter
whose time constants a small tree ensemble sets from the motion, exported as C99 (float32, no heap,
no globals written). Model `{Path(report['model_dir']).name}`, {mode}. Generated by
`togglecf.embedded.cvqf_toggling.export_c_vqf_toggling`; do not edit `src/` (export again).

```c
#include <tcf_vqf_toggling.h>
static tcf_vqft_t f;                          /* all state: one per sensor */
int rc = tcf_vqft_init(&f, 100.0f);           /* your IMU's rate [Hz]: TCF_OK (0) or an error code */
tcf_vqft_update_dt(&f, gyr, acc, mag, dt);    /* every sample; dt [s] since the previous one */
tcf_vqft_quat(&f, q);                         /* q = [w, x, y, z], sensor -> ENU */
```

See `examples/LearnedVQF/LearnedVQF.ino` (set `IMU_RATE_HZ`, replace `readImu()` with your driver).

**Rate at init.** `tcf_vqft_init(&f, fs)` takes the sampling rate `fs` [Hz], from 10 Hz (1/fs must not
exceed max_dt = 0.1 s) up to `TCF_MAX_FS` = {report['max_fs']:g} Hz, and derives every per-sample
coefficient from it: the settings are physical (time constants in seconds), as in the Python filter.
Above `TCF_MAX_FS` it returns `TCF_ERR_RATE_MAX` (-3): the feature window is a ring of
`TCF_WINDOW_MAX` = {report['window_max']} samples, the window at `TCF_MAX_FS`; export with a larger
`max_fs` for a faster IMU. `TCF_ERR_RATE` (-2): not a rate; `TCF_ERR_SETTINGS` (-1): below 10 Hz.

**Per-sample time step.** `tcf_vqft_update_dt(&f, gyr, acc, mag, dt)` integrates the gyro over the
actual `dt` [s] (jitter, lost samples; a dt that is not finite, <= 0 or > 0.1 s skips the gyro
integration of that sample). The low-pass filters, gains and timers and the features (which count
samples) run at the nominal rate of init, as in VQF. `tcf_vqft_update(&f, gyr, acc, mag)` uses dt = 1/fs.

**Units and frames.** gyr rad/s, acc m/s^2, mag uT (or `NULL`: no magnetometer), all in the sensor
frame; output quaternion [w, x, y, z] (Hamilton), sensor -> earth, earth frame ENU (x east, y north,
z up). Convert your driver's units (deg/s, g, Gauss) first.

**Memory.** `sizeof(tcf_vqft_t)` = {report['state_bytes']} bytes (`TCF_VQFT_STATE_BYTES`), of which
the feature ring 48 x `TCF_WINDOW_MAX` bytes; keep it static, not on a small task stack.{_size_line(report)}

**Build.** C99; the headers are C++-safe. Never compile with `-ffast-math` (the sources refuse it:
missing samples are NaN tests); `library.json` sets `-fno-fast-math` for PlatformIO.
"""
    return LibrarySpec(name="TogglecfLearnedVQF", example="LearnedVQF",
                       sentence="Learned VQF IMU orientation filter (togglecf): rate at init, float32, no heap.",
                       api_header=C_VQFT.api_header, files=LIBRARY_FILES, state_type=C_VQFT.state_type,
                       init="tcf_vqft_init({state}, {rate})", update="tcf_vqft_update_dt({state}, gyr, acc, mag, dt_s)",
                       quat="tcf_vqft_quat({state}, q)", readme=readme)


def _code_sizes(out_dir: Path) -> dict:
    """The size entries of the report (``export_c_vqf_toggling``): object sizes per source,
    ``code_bytes`` (text + data of all four), ``code_bytes_trees``, ``code_bytes_gc``, ``stack`` and
    the linked program sizes."""
    srcs = [out_dir / f for f in VQFT_SOURCES]
    obj = framework.per_source_sizes(out_dir, C_VQFT)

    def text_data(files, target):
        vals = [obj[f][target] for f in files]
        return None if any(v is None for v in vals) else sum(v["text"] + v["data"] for v in vals)

    targets = ("host", "riscv", "arm")
    main = framework.firmware_main(C_VQFT)
    return {"object_sizes": obj,
            "code_bytes": {t: text_data(VQFT_SOURCES, t) for t in targets},
            "code_bytes_trees": {t: text_data(["tcf_forest.c"], t) for t in targets},
            "code_bytes_gc": _reachable_code(srcs, out_dir),
            "stack": _stack(out_dir),
            "linked_riscv": link_riscv(srcs, [out_dir], main),
            "linked_arm": link_arm(srcs, [out_dir], main)}


def build_vqft_harness(out_dir, exe=None, cflags=framework.HARNESS_CFLAGS, defines=()) -> Path:
    """Compile ``tcf_vqf_toggling_harness`` from the sources in ``out_dir`` with the host gcc
    (``defines``: extra ``-D`` macros, e.g. ``TCF_ACC_T=double``); returns the executable
    (default ``out_dir/tcf_vqf_toggling_harness``)."""
    return framework.build_host_harness(out_dir, C_VQFT, exe, cflags, defines)


def run_vqft_harness(exe, gyr, acc, mag=None, *, diagnostics: bool = False, no_mag: bool = False,
                     predictions=None, fs=None, dt=None):
    """Run the compiled harness on ``(N, 3)`` arrays (``mag=None``: a 6-column CSV, the filter
    gets ``mag = NULL``; ``no_mag``: pass NULL although mag is given). Returns the quaternions
    ``(N, 4)`` float64, or with ``diagnostics`` ``(quat, dict)``: the held predictions
    (``p_<class>``, ``eta_acc_x`` ...), ``DIAG_NAMES`` per sample and ``ns_per_sample``.
    ``predictions (N, S + 6)``: drive steps 1-5 with these instead of the trees
    (``tcf_vqft_update_pred``; as ``VQFTogglingFilter.update_batch(..., predictions=...)``).
    ``fs`` [Hz]: the rate given to ``tcf_vqft_init`` (default ``TCF_DEFAULT_FS``); ``dt`` [s] (scalar
    or ``(N,)``): the per-sample time steps (``tcf_vqft_update_dt``; as ``update_batch(..., dt=...)``)."""
    return run_prediction_harness(exe, gyr, acc, mag, diagnostics=diagnostics, no_mag=no_mag,
                                  predictions=predictions, fs=fs, dt=dt)