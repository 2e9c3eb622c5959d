"""The toggling filter as a self-contained C99 source set (issue 6, "C implementation").

``export_c_filter(model_dir, out_dir, fs)`` writes into ``out_dir`` (e.g.
``build/embedded/NAME/filter/``):

* ``tcf_filter.h`` / ``tcf_filter.c``: hand-written port of ``toggling.inloop.inloop_batch`` (one sample)
  (streaming features, trees every hop, softmax, toggling step 1-7), float32, no heap, all
  state in one fixed-size ``tcf_filter_t`` (templates shipped in ``togglecf/embedded/``);
* ``tcf_config.h``: generated: rate, window, hop, EMA constants, the learned gains of
  ``gains.json`` (9D or 6D; time constants there, converted here to per-sample gains for the
  export rate ``fs``: k = 1 − exp(−1/(fs·τ)), the Python filter's coefficients at that rate),
  class names and the hashes of the model files it came from;
* ``tcf_forest.h`` / ``tcf_forest.c``: the merged forest (``export.forest_to_c``, outputs
  S class margins, η_a xyz, η_m xyz) without the trees the filter never uses (the outputs
  ``ModelTogglingFilter`` drops: η_a at noise weight 0; η_m in 6D, or at noise weight 0 without
  disturbance scaling). Leaf sums in float (``TCF_ACC_T``, set in ``tcf_config.h``);
* ``tcf_harness.c`` + ``Makefile``: a host program ``tcf_harness in.csv out.csv`` (CSV of
  gyr, acc[, mag] in rad/s, m/s², µT -> w,x,y,z), used by the tests to compare with Python;
* ``filter_report.json``: the returned report (files, state size, sizes).

``build_harness(out_dir)`` compiles the harness with gcc; ``run_harness(exe, gyr, acc, mag)``
runs it on arrays and returns the quaternions ``(N, 4)``.
"""
from __future__ import annotations

import hashlib
import json
import math
import subprocess
import tempfile
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from togglecf.core.io import atomic_write_json, atomic_write_text, file_sha256
from togglecf.embedded.forest_export import forest_to_c
from togglecf.embedded.toolchain import (
    c_float,
    link_riscv,
    measure_sizes,
    need_gcc,
    run_harness_command,
    run_prediction_harness,
    run_host_program,
    template,
    write_imu_csv,
)
from togglecf.features.windows import LAST_CHANNELS, WINDOW_CHANNELS, hop_length, window_length
from togglecf.toggling.gains import GAINS_FILE
from togglecf.toggling.load import load_toggling_filter

__all__ = ["export_c_filter", "ModelExport", "model_export", "write_forest", "build_harness", "run_harness", "harness_features", "TEMPLATES", "HARNESS_CFLAGS",
           "state_bytes_formula", "features_config", "fallback_config", "check_feature_layout", "check_export_rate",
           "FEATURE_TEMPLATES"]

#: the models in the loop (streaming features, range check, tree walk): shared with cvqf_toggling
FEATURE_TEMPLATES = ("tcf_features.h", "tcf_features.c")
TEMPLATES = ("tcf_filter.h", "tcf_filter.c", *FEATURE_TEMPLATES, "tcf_harness.c", "tcf_csv.h")
FILTER_SOURCES = ("tcf_filter.c", "tcf_features.c", "tcf_forest.c")
HARNESS_CFLAGS = ("-std=c99", "-O2", "-Wall", "-Wextra", "-pedantic")
#: the channel layout tcf_filter.c was written for (it hard-codes the ring columns)
_WINDOW_CHANNELS = ("gyr_x", "gyr_y", "gyr_z", "gyr_norm", "acc_x", "acc_y", "acc_z", "acc_norm_dev",
                    "jerk", "mag_norm_dev", "dip_dev")
_LAST_CHANNELS = ("gyr_norm", "acc_x", "acc_y", "acc_z", "acc_norm_dev", "mag_norm_dev", "dip_dev",
                  "acc_hp_x", "acc_hp_y", "acc_hp_z")
_FS_RTOL = 1e-3


def state_bytes_formula(window: int, n_classes: int) -> int:
    """``sizeof(tcf_filter_t)`` as documented in ``tcf_filter.h``: 4-byte members only,
    ``4 · (54 + 12 L + S)`` (54 = quaternion 4, bias 3, a_pred 3, m_pred 3, flag 1, EMA references
    as hi + lo 10, candidate field as hi + lo 4 and its count 1, previous acc 3, last-sample
    features 10, counters 3, η̂ 6, diagnostics 3; 12 L the ring; S the class probabilities)."""
    return 4 * (54 + 12 * int(window) + int(n_classes))






def _c_string(s: str) -> str:
    return '"' + str(s).replace("\\", "\\\\").replace('"', '\\"') + '"'


def fallback_config(models) -> tuple[str, dict]:
    """The ``tcf_config.h`` lines of the out-of-range fallback (``learn.ranges``, as
    ``CompiledModels`` holds it) and a summary for the report. Only the features with finite low
    and high enter (``TCF_BOUNDED_INIT``: their indices, written only when some feature is
    unbounded; when all are, the index is the feature's own and the table is left out, 1 byte per
    feature less); ``n_out > max_out_of_range · n_b`` is
    ``n_out > TCF_MAX_OUT`` with the integer ``floor(max_out_of_range · n_b)`` (the same float64
    product as Python). ``max_out_of_range >= 1`` (never falls back) or no bounded feature: 0
    bounded features, the check is compiled out."""
    low = np.asarray(getattr(models, "feature_low", np.full(models.forest.n_features, np.nan)), np.float64)
    high = np.asarray(getattr(models, "feature_high", np.full(models.forest.n_features, np.nan)), np.float64)
    max_out = float(getattr(models, "max_out_of_range", 1.0))
    idx = [j for j in range(low.size) if math.isfinite(low[j]) and math.isfinite(high[j])]
    limit = math.floor(max_out * len(idx)) if idx else 0
    if not idx or limit >= len(idx):
        idx = []
    info = {"n_bounded": len(idx), "max_out_of_range": max_out, "max_out": limit if idx else None}
    if not idx:
        return ("/* out-of-range fallback (togglecf.learn.ranges): off (no bounded feature, or max_out_of_range "
                f"{max_out:g} >= 1) */\n#define TCF_N_BOUNDED 0\n#define TCF_MAX_OUT 0\n"), info
    if max(idx) > 255:
        raise ValueError("the fallback's feature indices must fit uint8_t (at most 256 features)")

    def arr(vals):
        return "{" + ", ".join(vals) + "}"

    lines = [f"/* out-of-range fallback (togglecf.learn.ranges): more than TCF_MAX_OUT = floor({max_out:g} x "
             f"{len(idx)}) of the {len(idx)} bounded features",
             " * outside their training range -> no prediction (NaN) until the next window end; bounds rounded to "
             "float32 */",
             f"#define TCF_N_BOUNDED {len(idx)}",
             f"#define TCF_MAX_OUT {limit}",
             (f"#define TCF_BOUNDED_INIT {arr(str(j) for j in idx)}" if len(idx) < low.size else
              "/* every feature is bounded: feature j has bounds j (no index table, TCF_BOUNDED_INIT) */"),
             f"#define TCF_FEATURE_LOW_INIT {arr(c_float(low[j]) for j in idx)}",
             f"#define TCF_FEATURE_HIGH_INIT {arr(c_float(high[j]) for j in idx)}"]
    return "\n".join(lines) + "\n", info


def features_config(*, fs: float, window: int, hop: int, feat_params, models) -> str:
    """The ``tcf_config.h`` block of the models in the loop (``tcf_features.c``): rate, window,
    hop, EMA constants, gravity and the out-of-range fallback."""
    lam_ref, lam_lp, gravity = float(feat_params.ref_decay), float(feat_params.lp_decay), float(feat_params.gravity)
    fallback, _ = fallback_config(models)
    return f"""/* sampling: call the update once per sample at this rate */
#define TCF_FS {c_float(fs)}            /* Hz */
#define TCF_DT {c_float(1.0 / fs)}      /* s, 1 / TCF_FS */

/* features (togglecf.features.windows.FeatureSettings of the model) */
#define TCF_WINDOW {window}          /* samples per window, L */
#define TCF_HOP {hop}               /* samples between predictions, H */
#define TCF_LAM_REF {c_float(lam_ref)}     /* exp(-1 / (ref_tau_s fs)): |m| and dip reference and candidate */
#define TCF_LAM_REF_C {c_float(1.0 - lam_ref)}   /* 1 - TCF_LAM_REF (rounded from float64) */
#define TCF_REF_NORM_TH {c_float(feat_params.ref_norm_th)}   /* field agrees: ||m| - r| < this * r */
#define TCF_REF_DIP_TH {c_float(feat_params.ref_dip_th)}    /* rad, and |dip - d| < this */
#define TCF_REF_NEW_N {int(feat_params.ref_new_samples)}u     /* round(ref_new_s fs): rotating samples to take a new field */
#define TCF_REF_MIN_GYR_SQ {c_float(feat_params.ref_new_min_gyr_sq)}   /* (rad/s)^2: a sample counts as rotating from this |w|^2 */
#define TCF_LAM_LP {c_float(lam_lp)}      /* exp(-1 / (lp_tau_s fs)): acc low-pass */
#define TCF_LAM_LP_C {c_float(1.0 - lam_lp)}
#define TCF_GRAVITY {c_float(gravity)}     /* m/s^2, acc_norm_dev = |a| - g */

{fallback}
/* tree leaf sums in float32 (define TCF_ACC_T as double before this header for double sums) */
#ifndef TCF_ACC_T
#define TCF_ACC_T float
#endif
"""


def _config_header(*, model_dir: Path, fs: float, use_mag: bool, settings, params, class_names, static_index: int,
                   window: int, hop: int, feat_params, schema_hash: str, model_hash: str, gains_hash: str,
                   dropped, models) -> str:

    def arr(vals):
        return "{" + ", ".join(c_float(v) for v in vals) + "}"

    names = "{" + ", ".join(_c_string(c) for c in class_names) + "}"
    return f"""/* tcf_config.h: generated by togglecf.embedded.cfilter.export_c_filter; do not edit.
 * model directory: {model_dir.name}   mode: {'9D (acc + gyr + mag)' if use_mag else '6D (acc + gyr)'}
 * classes (order of the class probabilities): {', '.join(class_names)}
 * feature schema sha256: {schema_hash}
 * model files sha256 (metadata.json model_files): {model_hash}
 * gains.json sha256: {gains_hash}
 * trees not exported (outputs the filter never uses): {', '.join(dropped) or 'none'}
 */
#ifndef TCF_CONFIG_H
#define TCF_CONFIG_H

#define TCF_MODEL_ID {_c_string(model_dir.name + ':' + model_hash[:12] + ':' + gains_hash[:12])}

{features_config(fs=fs, window=window, hop=hop, feat_params=feat_params, models=models)}
#define TCF_MAX_DT {c_float(settings.max_dt)}   /* s, longest step still integrated */
#define TCF_USE_MAG {1 if use_mag else 0}

/* learned gains (gains.json, {'9d' if use_mag else '6d'}), per class in the order above: per-sample gains at
 * TCF_FS, k = 1 - exp(-TCF_DT / tau) of the learned time constants (this build is for TCF_FS only)
 * tau_acc [s] {', '.join(f'{t:g}' for t in settings.tau_acc)}; tau_mag [s] {', '.join(f'{t:g}' for t in settings.tau_mag)}
 * output_tau {settings.output_tau:g} s, bias_tau {settings.bias_tau:g} s */
#define TCF_ALPHA_ACC_INIT {arr(params.alpha_acc)}
#define TCF_ALPHA_MAG_INIT {arr(params.alpha_mag)}
#define TCF_GAMMA {c_float(params.gamma)}
#define TCF_BIAS_GAIN {c_float(params.bias_gain)}
#define TCF_BIAS_GATE {c_float(settings.bias_gate)}       /* rad/s */
#define TCF_STATIC_INDEX {static_index}     /* class in which the gyro bias is learned: {settings.static_state} */
#define TCF_MAG_DISTURBANCE_SCALE {c_float(settings.mag_disturbance_scale)}   /* uT, 0 = off */
#define TCF_NOISE_WEIGHT_ACC {c_float(settings.noise_weight_acc)}
#define TCF_NOISE_WEIGHT_MAG {c_float(settings.noise_weight_mag)}
/* the fallback (no prediction, or top probability below TCF_CONFIDENCE_FLOOR of the sum): the cautious
 * gains, per sensor the smallest of the per-class ones above */
#define TCF_CONFIDENCE_FLOOR {c_float(settings.confidence_floor)}
#define TCF_ALPHA_FALLBACK_ACC {c_float(params.alpha_fallback_acc)}
#define TCF_ALPHA_FALLBACK_MAG {c_float(params.alpha_fallback_mag)}
#define TCF_CLASS_NAMES_INIT {names}

#endif /* TCF_CONFIG_H */
"""


_MAKEFILE = """# Host build of the exported toggling filter (see tcf_filter.h). For a firmware build, add
# tcf_filter.c, tcf_features.c and tcf_forest.c (+ the four headers) to the project; no other file is needed.
CC ?= gcc
CFLAGS ?= {cflags}

tcf_harness: tcf_harness.c tcf_csv.h tcf_filter.c tcf_features.c tcf_forest.c tcf_filter.h tcf_features.h tcf_forest.h \\
\t\ttcf_config.h
\t$(CC) $(CFLAGS) -o $@ tcf_harness.c tcf_filter.c tcf_features.c tcf_forest.c -lm

clean:
\trm -f tcf_harness

.PHONY: clean
"""

_SIZE_MAIN = r"""
#include <stdio.h>
#include "tcf_filter.h"
int main(void) {
  printf("%u %u\n", (unsigned)sizeof(tcf_filter_t), (unsigned)TCF_STATE_BYTES);
  return 0;
}
"""

_RISCV_MAIN = r"""
#include "tcf_filter.h"
volatile float tcf_in[9];
float tcf_q[4];
static tcf_filter_t tcf_f;
int main(void) {
  float g[3], a[3], m[3];
  int i;
  tcf_filter_init(&tcf_f);
  for (i = 0; i < 3; ++i) { g[i] = tcf_in[i]; a[i] = tcf_in[3 + i]; m[i] = tcf_in[6 + i]; }
  tcf_filter_update(&tcf_f, g, a, m);
  tcf_filter_quat(&tcf_f, tcf_q);
  return (int)tcf_q[0];
}
"""


def check_feature_layout():
    if tuple(WINDOW_CHANNELS) != _WINDOW_CHANNELS or tuple(LAST_CHANNELS) != _LAST_CHANNELS:
        raise RuntimeError("togglecf.features.windows changed its channels: update togglecf/embedded/tcf_features.c "
                           "(tcf_push_sample) and cfilter._WINDOW_CHANNELS/_LAST_CHANNELS to match")


def _measure_state_bytes(out_dir: Path) -> tuple[int, int]:
    """``sizeof(tcf_filter_t)`` and the documented ``TCF_STATE_BYTES`` (host gcc)."""
    size, documented = run_host_program(_SIZE_MAIN, [out_dir], "measuring sizeof(tcf_filter_t)").split()
    return int(size), int(documented)


def check_export_rate(model_dir, fs) -> tuple[dict, float]:
    """The checks every filter export makes: ``model_dir`` is a model directory with
    ``gains.json``, ``fs`` a positive rate equal to the models' ``sampling_rate`` (the features
    were learned at it). Returns (metadata, fs as float)."""
    model_dir = Path(model_dir)
    meta_path = model_dir / "metadata.json"
    if not meta_path.is_file():
        raise FileNotFoundError(f"{meta_path}: not a model directory (run `togglecf train`)")
    gains_path = model_dir / GAINS_FILE
    if not gains_path.is_file():
        raise FileNotFoundError(f"{gains_path}: no learned gains; the C filter needs them "
                                "(`togglecf train` learns them, or gains.save_gains)")
    if not (isinstance(fs, (int, float, np.floating)) and math.isfinite(fs) and fs > 0):
        raise ValueError(f"fs must be a positive sampling rate in Hz, got {fs!r}")
    fs = float(fs)
    meta = json.loads(meta_path.read_text())
    sr = meta.get("sampling_rate")
    if sr is not None and abs(fs / float(sr) - 1.0) > _FS_RTOL:
        raise ValueError(f"fs = {fs:g} Hz differs from the models' sampling_rate {float(sr):g} Hz in {meta_path}: "
                         "the models' features were learned at that rate; export for "
                         f"fs={float(sr):g} (and resample the IMU to it) or retrain at {fs:g} Hz")
    return meta, fs


@dataclass
class ModelExport:
    """What both C exports of a trained filter take from its model directory: the Python filter
    with its models (``filt``), the class names, the forest it walks and the outputs it drops,
    window and hop [samples] at the export rate, and the hashes the generated files record."""

    filt: object
    classes: list
    forest: object
    dropped: list
    window: int
    hop: int
    model_hash: str
    gains_hash: str
    schema_hash: str


def model_export(model_dir: Path, meta: dict, fs: float, filt) -> ModelExport:
    """The ``ModelExport`` of ``filt`` (loaded from ``model_dir`` at rate ``fs``; ``meta`` its
    ``metadata.json``); refuses a rate at which the gyro would never be integrated."""
    s = filt.settings
    if not 1.0 / fs <= s.max_dt:
        raise ValueError(f"1/fs = {1 / fs:g} s exceeds max_dt = {s.max_dt:g} s: the gyro would never be integrated")
    classes = list(filt.models.class_names)
    k = len(classes)
    out_names = classes + [f"eta_{t}_{ax}" for t in ("acc", "mag") for ax in "xyz"]
    forest = filt.forest  # the trees the Python filter walks (outputs it never uses dropped)
    kept = {int(g) for g in np.unique(forest.tree_group)}
    dropped = [out_names[i] for i in range(k, k + 6) if i not in kept]
    fset = filt.models.feature_settings
    L, hop = window_length(fs, fset.window_s), hop_length(fs, fset.hop_s)
    if (L, hop) != (filt.streaming_features.L, filt.hop):
        raise AssertionError("window/hop of the Python filter and the export disagree")
    return ModelExport(filt, classes, forest, dropped, L, hop,
                       model_hash=hashlib.sha256(json.dumps(meta.get("model_files", {}), sort_keys=True).encode())
                       .hexdigest(),
                       gains_hash=file_sha256(model_dir / GAINS_FILE),
                       schema_hash=meta.get("feature_schema", {}).get("hash", "?"))


def write_forest(out_dir: Path, model_dir: Path, ex: ModelExport) -> tuple[list, int]:
    """``tcf_forest.h`` / ``tcf_forest.c`` (the trees ``ex.filt`` walks, leaf sums in
    ``TCF_ACC_T`` of ``tcf_config.h``) in ``out_dir``: returns the paths and the node count."""
    comment = (f"model {model_dir.resolve().name}: outputs {', '.join(ex.classes)} (margins), eta_acc xyz, eta_mag xyz"
               + (f"; trees of {', '.join(ex.dropped)} not exported (base margin only)" if ex.dropped else ""))
    header, source = forest_to_c(ex.forest, "tcf_", len(ex.classes), comment)
    files = [atomic_write_text(out_dir / "tcf_forest.h", header),
             atomic_write_text(out_dir / "tcf_forest.c",
                               '#include "tcf_config.h" /* TCF_ACC_T: type of the leaf sums */\n' + source)]
    return files, int(header.split("#define TCF_N_NODES ")[1].split()[0])


def export_c_filter(model_dir, out_dir, fs: float, use_mag: bool = True, riscv: bool = True) -> dict:
    """Write the C filter of ``model_dir`` (a ``togglecf train`` directory with ``gains.json``)
    for sampling rate ``fs`` [Hz] into ``out_dir``; returns the report (also written as
    ``out_dir/filter_report.json``): ``files``, ``state_bytes`` (sizeof(tcf_filter_t), measured
    with gcc), ``object_sizes`` and, with the RISC-V toolchain, ``linked_riscv`` (an rv32imc
    picolibc program calling init/update: its ``flash`` = text + data bytes)."""
    model_dir, out_dir = Path(model_dir), Path(out_dir)
    meta, fs = check_export_rate(model_dir, fs)
    check_feature_layout()
    filt = load_toggling_filter(model_dir, fs, use_mag=use_mag)
    ex = model_export(model_dir, meta, fs, filt)
    s, classes, forest, dropped, L, hop, k = ex.filt.settings, ex.classes, ex.forest, ex.dropped, ex.window, ex.hop, \
        len(ex.classes)
    model_hash, gains_hash, schema_hash = ex.model_hash, ex.gains_hash, ex.schema_hash
    out_dir.mkdir(parents=True, exist_ok=True)
    files = [atomic_write_text(out_dir / name, template(name)) for name in TEMPLATES]
    files.append(atomic_write_text(out_dir / "tcf_config.h", _config_header(
        model_dir=model_dir.resolve(), fs=fs, use_mag=use_mag, settings=s, params=filt.params, class_names=classes,
        static_index=s.states.index(s.static_state), window=L, hop=hop, feat_params=filt.streaming_features.params,
        schema_hash=schema_hash, model_hash=model_hash, gains_hash=gains_hash, dropped=dropped, models=filt.models)))
    forest_files, n_nodes = write_forest(out_dir, model_dir, ex)
    files += forest_files
    files.append(atomic_write_text(out_dir / "Makefile", _MAKEFILE.format(cflags=" ".join(HARNESS_CFLAGS))))

    report = {"out_dir": str(out_dir), "model_dir": str(model_dir), "files": [str(p) for p in files],
              "fs": fs, "use_mag": bool(use_mag), "window": L, "hop": hop, "n_classes": k, "class_names": classes,
              "n_features": int(forest.n_features), "n_trees": int(len(forest.roots)), "n_nodes": n_nodes,
              "dropped_outputs": dropped, "settings": asdict(s),
              "per_sample_gains": {"alpha_acc": filt.params.alpha_acc.tolist(), "alpha_mag": filt.params.alpha_mag.tolist(),
                                   "gamma": float(filt.params.gamma), "bias_gain": float(filt.params.bias_gain),
                                   "alpha_fallback_acc": float(filt.params.alpha_fallback_acc),
                                   "alpha_fallback_mag": float(filt.params.alpha_fallback_mag)},
              "schema_hash": schema_hash,
              "model_hash": model_hash, "gains_sha256": gains_hash,
              "fallback": fallback_config(filt.models)[1],
              "state_bytes_formula": "4 * (54 + 12 * window + n_classes)",
              "state_bytes_documented": state_bytes_formula(L, k)}
    size, documented = _measure_state_bytes(out_dir)
    if documented != report["state_bytes_documented"]:
        raise AssertionError(f"TCF_STATE_BYTES {documented} != state_bytes_formula {report['state_bytes_documented']}")
    report["state_bytes"] = size
    sizes = measure_sizes([out_dir / f for f in FILTER_SOURCES], [out_dir], riscv=riscv)
    report["object_sizes"] = {Path(f).name: v for f, v in sizes.items()}
    report["linked_riscv"] = (link_riscv([out_dir / f for f in FILTER_SOURCES], [out_dir], _RISCV_MAIN)
                              if riscv else None)
    atomic_write_json(out_dir / "filter_report.json", report)
    return report


def build_harness(out_dir, exe=None, cflags=HARNESS_CFLAGS) -> Path:
    """Compile ``tcf_harness`` from the sources in ``out_dir`` with the host gcc; returns the
    executable (default ``out_dir/tcf_harness``). Raises ``RuntimeError`` with gcc's output."""
    out_dir = Path(out_dir)
    gcc = need_gcc("building the C filter's harness")
    missing = [f for f in ("tcf_harness.c", "tcf_csv.h", *FILTER_SOURCES, "tcf_filter.h", "tcf_features.h", "tcf_forest.h",
                           "tcf_config.h")
               if not (out_dir / f).is_file()]
    if missing:
        raise FileNotFoundError(f"{out_dir}: missing {', '.join(missing)} (run export_c_filter first)")
    exe = Path(exe) if exe is not None else out_dir / "tcf_harness"
    cmd = [gcc, *cflags, "-o", str(exe), *(str(out_dir / f) for f in ("tcf_harness.c", *FILTER_SOURCES)),
           f"-I{out_dir}", "-lm"]
    res = subprocess.run(cmd, capture_output=True, text=True)
    if res.returncode != 0:
        raise RuntimeError(f"compiling the harness failed: {' '.join(cmd)}\n{res.stderr[-4000:]}")
    return exe






def run_harness(exe, gyr, acc, mag=None, *, diagnostics: bool = False, no_mag: bool = False, predictions=None):
    """Run the compiled harness on ``(N, 3)`` arrays (``mag=None``: a 6-column CSV, the filter
    gets ``mag = NULL``; ``no_mag``: pass NULL although mag is given). Returns the quaternions
    ``(N, 4)`` float64, or with ``diagnostics`` ``(quat, dict)`` with the held predictions
    (``p_<class>``, ``eta_acc_x`` ...), ``alpha_acc``, ``alpha_mag`` per sample and the filter's
    ``ns_per_sample`` (the harness's clock() timing of the update calls).
    ``predictions (N, S + 6)``: drive the toggling step with these instead of the trees
    (``tcf_filter_update_pred``; as ``TogglingFilter.update_batch(..., predictions=...)``)."""
    return run_prediction_harness(exe, gyr, acc, mag, diagnostics=diagnostics, no_mag=no_mag,
                                  predictions=predictions)


def harness_features(exe, gyr, acc, mag=None):
    """The C filter's feature rows at its window ends: ``(ends (n,), X (n, F))`` float64, to
    compare with ``features.compute_features`` (``tcf_harness --features``)."""
    with tempfile.TemporaryDirectory() as tmp:
        fin, fout, ffeat = Path(tmp) / "in.csv", Path(tmp) / "out.csv", Path(tmp) / "feat.csv"
        write_imu_csv(fin, gyr, acc, mag)
        run_harness_command(exe, [str(exe), "--features", str(ffeat), str(fin), str(fout)])
        F = np.loadtxt(ffeat, delimiter=",", ndmin=2)
    return F[:, 0].astype(np.int64), F[:, 1:]
