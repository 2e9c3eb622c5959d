"""The VQF core with learned time constants (``togglecf.toggling.inloop.ModelVQFTogglingFilter``)
as a self-contained C99 source set (issue 13, item 5).

``export_c_vqf_toggling(model_dir, out_dir, fs, use_mag=True)`` writes into ``out_dir``:

* the shared C pieces, unchanged templates of ``togglecf/embedded/``: ``tcf_features.{h,c}``
  (the models in the loop: streaming features, the out-of-range check, the tree walk; the same
  file the toggling CF export ships) and ``tcf_vqf.{h,c}`` (the VQF core of ``export_c_vqf``;
  ``tcf_vqf_update_mod`` runs it with modulated coefficients);
* ``tcf_vqf_toggling.{h,c}``: steps 1-5 of ``filters.vqf_toggling`` (probabilities -> blended
  ln τ_acc, ln τ_mag, ln σ_motion with confidence λ -> coefficients, recomputed only when the
  probabilities change; noise removal; the core step), float32, no heap, one fixed-size
  ``tcf_vqft_t``;
* ``tcf_config.h`` (generated: rate, window, hop, EMA constants, the out-of-range fallback's
  feature bounds, class names, the per-state values as natural logarithms ``TCF_VQFT_LN_*``,
  confidence floor, noise weights, model/gains hashes) and ``tcf_vqf_config.h`` (the core's
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

from togglecf.core.io import atomic_write_json, atomic_write_text
from togglecf.embedded.cfilter import (
    FEATURE_TEMPLATES,
    HARNESS_CFLAGS,
    check_export_rate,
    check_feature_layout,
    fallback_config,
    features_config,
    model_export,
    write_forest,
)
from togglecf.embedded.cvqf import vqf_config_header
from togglecf.embedded.toolchain import (
    ARM_FLAGS,
    ARM_GCC,
    ARM_SIZE,
    RISCV_GCC,
    arm_available,
    arm_object_size,
    c_float,
    link_arm,
    link_riscv,
    measure_sizes,
    need_gcc,
    reachable_code_size,
    riscv_flags,
    run_command,
    run_prediction_harness,
    run_host_program,
    template,
    unit_chain_stack,
)
from togglecf.toggling.gains import GAINS_FILE
from togglecf.toggling.load import load_toggling_filter

__all__ = ["export_c_vqf_toggling", "build_vqft_harness", "run_vqft_harness", "VQFT_TEMPLATES", "VQFT_SOURCES",
           "state_bytes_formula", "DIAG_NAMES"]

VQFT_TEMPLATES = ("tcf_vqf_toggling.h", "tcf_vqf_toggling.c", *FEATURE_TEMPLATES, "tcf_vqf.h", "tcf_vqf.c",
                  "tcf_vqf_toggling_harness.c", "tcf_csv.h")
#: the firmware sources: filter + trees (the object code of the 32 KB goal)
VQFT_SOURCES = ("tcf_vqf_toggling.c", "tcf_features.c", "tcf_vqf.c", "tcf_forest.c")
#: columns of ``--diag`` after the predictions
DIAG_NAMES = ("tau_acc", "tau_mag", "trust", "fallback", "rest", "mag_dist")

_MAKEFILE = """# Host build of the exported learned VQF filter (see tcf_vqf_toggling.h). For a firmware build,
# add {sources} (+ the headers tcf_vqf_toggling.h tcf_features.h tcf_vqf.h
# tcf_forest.h tcf_config.h tcf_vqf_config.h) to the project; nothing else. Never -ffast-math.
CC ?= gcc
CFLAGS ?= {cflags}
SRC = {sources}

tcf_vqf_toggling_harness: tcf_vqf_toggling_harness.c tcf_csv.h $(SRC) tcf_vqf_toggling.h tcf_features.h tcf_vqf.h \\
\t\ttcf_forest.h tcf_config.h tcf_vqf_config.h
\t$(CC) $(CFLAGS) -o $@ tcf_vqf_toggling_harness.c $(SRC) -lm

clean:
\trm -f tcf_vqf_toggling_harness

.PHONY: clean
"""

_SIZE_MAIN = r"""
#include <stdio.h>
#include "tcf_vqf_toggling.h"
int main(void) {
  printf("%u %u %u %u\n", (unsigned)sizeof(tcf_vqft_t), (unsigned)TCF_VQFT_STATE_BYTES,
         (unsigned)sizeof(tcf_features_t), (unsigned)sizeof(tcf_vqf_t));
  return 0;
}
"""

_LINK_MAIN = r"""
#include "tcf_vqf_toggling.h"
volatile float tcf_in[9];
float tcf_q[4];
static tcf_vqft_t tcf_f;
int main(void) {
  float g[3], a[3], m[3];
  int i;
  if (tcf_vqft_init(&tcf_f) != 0) return 1;
  for (i = 0; i < 3; ++i) { g[i] = tcf_in[i]; a[i] = tcf_in[3 + i]; m[i] = tcf_in[6 + i]; }
  tcf_vqft_update(&tcf_f, g, a, m);
  tcf_vqft_quat(&tcf_f, tcf_q);
  return (int)tcf_q[0];
}
"""

#: one translation unit of the four sources, for the stack of the whole tcf_vqft_update chain


def state_bytes_formula(window: int, n_classes: int) -> int:
    """``sizeof(tcf_vqft_t)`` as documented in ``tcf_vqf_toggling.h``: the core's 532 bytes, the
    features ``4 · (37 + 12 L + S)`` (ring 12 L; EMA references 10, candidate field 5, previous acc
    3, last-sample features 10, counters 3, η̂ 6; class probabilities S) and ``4 · (22 + S)``
    (modulation 7, diagnostics 3, the last prediction S + 6, the followed modulation and back-off 6)."""
    return 532 + 4 * (37 + 12 * int(window) + int(n_classes)) + 4 * (22 + int(n_classes))


def _c_string(s: str) -> str:
    return '"' + str(s).replace("\\", "\\\\").replace('"', '\\"') + '"'


def _config_header(*, model_dir: Path, fs: float, use_mag: bool, filt, window: int, hop: int, schema_hash: str,
                   model_hash: str, gains_hash: str, dropped) -> str:
    s, p = filt.settings, filt.params
    classes = list(filt.models.class_names)

    def arr(vals):
        return "{" + ", ".join(c_float(v) for v in vals) + "}"

    names = "{" + ", ".join(_c_string(c) for c in classes) + "}"
    return f"""/* tcf_config.h: generated by togglecf.embedded.cvqf_toggling.export_c_vqf_toggling; do not edit.
 * model directory: {model_dir.name}   mode: {'9D (acc + gyr + mag)' if use_mag else '6D (acc + gyr)'}
 * filter: VQF core with learned time constants (gains.json, {'vqf_9d' if use_mag else 'vqf_6d'})
 * classes (order of the class probabilities): {', '.join(classes)}
 * feature schema sha256: {schema_hash}
 * model files sha256 (metadata.json model_files): {model_hash}
 * gains.json sha256: {gains_hash}
 * trees not exported (outputs the filter never uses): {', '.join(dropped) or 'none'}
 */
#ifndef TCF_CONFIG_H
#define TCF_CONFIG_H

#define TCF_MODEL_ID {_c_string(model_dir.name + ':' + model_hash[:12] + ':' + gains_hash[:12])}

{features_config(fs=fs, window=window, hop=hop, feat_params=filt.streaming_features.params, models=filt.models)}
#define TCF_USE_MAG {1 if use_mag else 0}   /* the core's use_mag (tcf_vqf_config.h) */
#define TCF_CLASS_NAMES_INIT {names}

/* learned time constants (filters.vqf_toggling, steps 1-3), per class in the order above, as
 * natural logarithms (the blend is in ln tau): tau_acc [s] {', '.join(f'{t:g}' for t in s.tau_acc_states)};
 * tau_mag [s] {', '.join(f'{t:g}' for t in s.tau_mag_states)}; sigma_motion [deg/s] {', '.join(f'{t:g}' for t in s.bias_sigma_motion_states)}
 * (ln of rad/s). The core's own values (the fallback: no prediction, or low confidence):
 * tau_acc {s.tau_acc:g} s, tau_mag {s.tau_mag:g} s, sigma_motion {s.bias_sigma_motion:g} deg/s. */
#define TCF_VQFT_LN_TAU_ACC_INIT {arr(p.ln_tau_acc)}
#define TCF_VQFT_LN_TAU_MAG_INIT {arr(p.ln_tau_mag)}
#define TCF_VQFT_LN_SIGMA_MOTION_INIT {arr(p.ln_sigma_motion)}
#define TCF_VQFT_LN_TAU_ACC_CORE {c_float(p.ln_tau_acc_core)}
#define TCF_VQFT_LN_TAU_MAG_CORE {c_float(p.ln_tau_mag_core)}
#define TCF_VQFT_LN_SIGMA_MOTION_CORE {c_float(p.ln_sigma_motion_core)}
/* rest thresholds per class, as natural logarithms: th_omega [deg/s] {', '.join(f'{t:g}' for t in s.rest_th_gyr_states)}
 * (ln of rad/s), th_a [m/s^2] {', '.join(f'{t:g}' for t in s.rest_th_acc_states)}; the core's: {s.rest_th_gyr:g} deg/s, {s.rest_th_acc:g} m/s^2 */
#define TCF_VQFT_LN_REST_TH_GYR_INIT {arr(p.ln_rest_th_gyr)}
#define TCF_VQFT_LN_REST_TH_ACC_INIT {arr(p.ln_rest_th_acc)}
#define TCF_VQFT_LN_REST_TH_GYR_CORE {c_float(p.ln_rest_th_gyr_core)}
#define TCF_VQFT_LN_REST_TH_ACC_CORE {c_float(p.ln_rest_th_acc_core)}
/* sigma_m [uT] of step 3 (heading gain / (1 + (|eta_m| / sigma_m)^2)); 0: off (always 0 in 6D) */
#define TCF_VQFT_MAG_DIST_SCALE {c_float(p.mag_disturbance_scale)}
/* mag_backoff_measured: the back-off acts on at most the disturbance the magnetometer shows */
#define TCF_VQFT_BACKOFF_MEASURED {1 if s.mag_backoff_measured else 0}
#define TCF_VQFT_CONFIDENCE_FLOOR {c_float(s.confidence_floor)}   /* c0 of step 1 */
#define TCF_VQFT_NOISE_WEIGHT_ACC {c_float(s.noise_weight_acc)}   /* w_a of step 4 */
#define TCF_VQFT_NOISE_WEIGHT_MAG {c_float(s.noise_weight_mag)}   /* w_m of step 4 */
#define TCF_VQFT_NOISE_ACC {1 if s.noise_weight_acc != 0 else 0}   /* 0: w_a = 0, step 4 leaves acc as is (a - 0 eta = a) */
#define TCF_VQFT_NOISE_MAG {1 if s.noise_weight_mag != 0 else 0}   /* 0: w_m = 0, step 4 leaves mag as is */
/* modulation_tau {s.modulation_tau:g} s: ln tau_acc, ln tau_mag follow the blended values with this per-sample gain
 * (1 - exp(-Ts / modulation_tau) at TCF_FS); TCF_VQFT_FOLLOW 0: at once (modulation_tau 0) */
#define TCF_VQFT_FOLLOW {1 if p.modulation_gain < 1.0 else 0}
#define TCF_VQFT_MODULATION_GAIN {c_float(p.modulation_gain)}

#endif /* TCF_CONFIG_H */
"""


#: the API a firmware calls (as _LINK_MAIN): the roots of ``code_bytes_gc``
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


def export_c_vqf_toggling(model_dir, out_dir, fs: float, use_mag: bool = True, *, sizes: bool = True) -> dict:
    """Write the learned VQF filter of ``model_dir`` (a ``togglecf train`` directory whose
    ``gains.json`` has ``vqf_9d`` / ``vqf_6d``) for rate ``fs`` [Hz] (= the models'
    ``sampling_rate``) into ``out_dir``; returns the report (also
    ``out_dir/vqf_toggling_report.json``): ``files``, ``state_bytes`` (sizeof(tcf_vqft_t), gcc),
    ``fallback`` (the out-of-range rule as exported) and, with ``sizes``, ``object_sizes``
    {source: {host, riscv, arm}} (-Os; None where a cross compiler is missing), ``code_bytes``
    {host, riscv, arm}: text + data of the four objects of trees + filter (the measure of the
    32 KB goal), ``code_bytes_trees`` (tcf_forest.c alone), ``code_bytes_gc``: the same four
    compiled with ``-ffunction-sections`` and kept by ``--gc-sections`` from
    ``tcf_vqft_init`` / ``tcf_vqft_update`` / ``tcf_vqft_quat`` (the unused API dropped; libm and
    soft-float still not counted), ``stack`` {riscv, arm} of the ``tcf_vqft_update`` chain,
    ``linked_riscv`` / ``linked_arm`` program sizes (with libm, soft-float and start-up)."""
    model_dir, out_dir = Path(model_dir), Path(out_dir)
    meta, fs = check_export_rate(model_dir, fs)
    check_feature_layout()
    try:
        filt = load_toggling_filter(model_dir, fs, use_mag=use_mag, kind="vqf_toggling")
    except KeyError as e:
        raise ValueError(f"{model_dir / GAINS_FILE}: no {'vqf_9d' if use_mag else 'vqf_6d'} gains "
                         f"(add it to [gains] modes and retrain): {e}") from None
    ex = model_export(model_dir, meta, fs, filt)
    s, classes, forest, dropped, L, hop, k = ex.filt.settings, ex.classes, ex.forest, ex.dropped, ex.window, ex.hop, \
        len(ex.classes)
    model_hash, gains_hash, schema_hash = ex.model_hash, ex.gains_hash, ex.schema_hash

    out_dir.mkdir(parents=True, exist_ok=True)
    files = [atomic_write_text(out_dir / name, template(name)) for name in VQFT_TEMPLATES]
    files.append(atomic_write_text(out_dir / "tcf_config.h", _config_header(
        model_dir=model_dir.resolve(), fs=fs, use_mag=use_mag, filt=filt, window=L, hop=hop, schema_hash=schema_hash,
        model_hash=model_hash, gains_hash=gains_hash, dropped=dropped)))
    files.append(atomic_write_text(out_dir / "tcf_vqf_config.h", vqf_config_header(fs, s.core_settings, use_mag)))
    forest_files, n_nodes = write_forest(out_dir, model_dir, ex)
    files += forest_files
    files.append(atomic_write_text(out_dir / "Makefile", _MAKEFILE.format(cflags=" ".join(HARNESS_CFLAGS),
                                                                          sources=" ".join(VQFT_SOURCES))))

    report = {"out_dir": str(out_dir), "model_dir": str(model_dir), "files": [str(p) for p in files], "fs": fs,
              "use_mag": bool(use_mag), "window": L, "hop": hop, "n_classes": k, "class_names": classes,
              "n_features": int(forest.n_features), "n_trees": int(len(forest.roots)), "n_nodes": n_nodes,
              "dropped_outputs": dropped, "settings": asdict(s), "fallback": fallback_config(filt.models)[1],
              "schema_hash": schema_hash, "model_hash": model_hash, "gains_sha256": gains_hash,
              "coefficients": "core: derived in C by tcf_vqf_init; modulation: tcf_vqf_mod_from at each "
                              "probability change (float32)"}
    size, documented, feat_size, core_size = (int(v) for v in run_host_program(
        _SIZE_MAIN, [out_dir], "measuring sizeof(tcf_vqft_t)").split())
    if not size == documented == state_bytes_formula(L, k):
        raise AssertionError(f"sizeof(tcf_vqft_t) {size}, TCF_VQFT_STATE_BYTES {documented} and "
                             f"state_bytes_formula {state_bytes_formula(L, k)} disagree")
    report["state_bytes"] = size
    report["state_bytes_parts"] = {"core": core_size, "features": feat_size, "learned": size - core_size - feat_size}
    if sizes:
        srcs = [out_dir / f for f in VQFT_SOURCES]
        measured = measure_sizes(srcs, [out_dir], riscv=True)
        obj = {}
        for f in srcs:
            m = measured[str(f)]
            obj[f.name] = {"host": m["host"], "riscv": m["riscv"], "arm": arm_object_size(f, [out_dir])}
        report["object_sizes"] = obj

        def code(target):
            vals = [obj[f][target] for f in VQFT_SOURCES]
            return None if any(v is None for v in vals) else sum(v["text"] + v["data"] for v in vals)

        report["code_bytes"] = {t: code(t) for t in ("host", "riscv", "arm")}
        report["code_bytes_trees"] = {t: (None if obj["tcf_forest.c"][t] is None else
                                          obj["tcf_forest.c"][t]["text"] + obj["tcf_forest.c"][t]["data"])
                                      for t in ("host", "riscv", "arm")}
        report["code_bytes_gc"] = _reachable_code(srcs, out_dir)
        report["stack"] = _stack(out_dir)
        report["linked_riscv"] = link_riscv(srcs, [out_dir], _LINK_MAIN)
        report["linked_arm"] = link_arm([out_dir / f for f in VQFT_SOURCES], [out_dir], _LINK_MAIN)
    atomic_write_json(out_dir / "vqf_toggling_report.json", report)
    return report


def build_vqft_harness(out_dir, exe=None, cflags=HARNESS_CFLAGS, defines=()) -> Path:
    """Compile ``tcf_vqf_toggling_harness`` from the sources in ``out_dir`` with the host gcc
    (``defines``: extra ``-D`` macros, e.g. ``TCF_ACC_T=double``); returns the executable
    (default ``out_dir/tcf_vqf_toggling_harness``)."""
    out_dir = Path(out_dir)
    gcc = need_gcc("building the learned VQF filter's harness")
    missing = [f for f in (*VQFT_TEMPLATES, "tcf_config.h", "tcf_vqf_config.h", "tcf_forest.h", "tcf_forest.c")
               if not (out_dir / f).is_file()]
    if missing:
        raise FileNotFoundError(f"{out_dir}: missing {', '.join(missing)} (run export_c_vqf_toggling first)")
    exe = Path(exe) if exe is not None else out_dir / "tcf_vqf_toggling_harness"
    run_command([gcc, *cflags, *(f"-D{d}" for d in defines), "-o", exe, out_dir / "tcf_vqf_toggling_harness.c",
                 *(out_dir / s for s in VQFT_SOURCES), f"-I{out_dir}", "-lm"])
    return exe


def run_vqft_harness(exe, gyr, acc, mag=None, *, diagnostics: bool = False, no_mag: bool = False,
                     predictions=None):
    """Run the compiled harness on ``(N, 3)`` arrays (``mag=None``: a 6-column CSV, the filter
    gets ``mag = NULL``; ``no_mag``: pass NULL although mag is given). Returns the quaternions
    ``(N, 4)`` float64, or with ``diagnostics`` ``(quat, dict)``: the held predictions
    (``p_<class>``, ``eta_acc_x`` ...), ``DIAG_NAMES`` per sample and ``ns_per_sample``.
    ``predictions (N, S + 6)``: drive steps 1-5 with these instead of the trees
    (``tcf_vqft_update_pred``; as ``VQFTogglingFilter.update_batch(..., predictions=...)``)."""
    return run_prediction_harness(exe, gyr, acc, mag, diagnostics=diagnostics, no_mag=no_mag,
                                  predictions=predictions)