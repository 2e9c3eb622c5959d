"""What both exports of a *learned* filter share (``cfilter``: the toggling CF; ``cvqf_toggling``:
the VQF core with learned time constants): the checks of the model directory and rate, the
models in the loop (``tcf_features.{h,c}``: their ``tcf_config.h`` block with the out-of-range
fallback; the forest ``tcf_forest.{h,c}``) and the head of ``tcf_config.h`` naming the model
files it came from.
"""
from __future__ import annotations

import hashlib
import json
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from togglecf.core.io import atomic_write_text, file_sha256
from togglecf.embedded.forest_export import forest_to_c
from togglecf.embedded.framework import c_float_array, c_string
from togglecf.embedded.toolchain import c_float
from togglecf.features.windows import LAST_CHANNELS, WINDOW_CHANNELS, hop_length, window_length
from togglecf.toggling.gains import GAINS_FILE, mode_name
from togglecf.toggling.load import load_toggling_filter

__all__ = ["FEATURE_TEMPLATES", "ModelExport", "load_model_export", "model_export", "check_export_rate",
           "check_feature_layout", "fallback_config", "features_config", "write_forest", "learned_config"]

#: the models in the loop (streaming features, range check, tree walk), shipped with every learned filter
FEATURE_TEMPLATES = ("tcf_features.h", "tcf_features.c")
#: the channel layout tcf_filter.c was written for (it hard-codes the ring columns)
_WINDOW_CHANNELS = ("gyr_x", "gyr_y", "gyr_z", "gyr_norm", "acc_x", "acc_y", "acc_z", "acc_norm_dev",
                    "jerk", "mag_norm_dev", "dip_dev")
_LAST_CHANNELS = ("gyr_norm", "acc_x", "acc_y", "acc_z", "acc_norm_dev", "mag_norm_dev", "dip_dev",
                  "acc_hp_x", "acc_hp_y", "acc_hp_z")
_FS_RTOL = 1e-3


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

    lines = [f"/* out-of-range fallback (togglecf.learn.ranges): more than TCF_MAX_OUT = floor({max_out:g} x "
             f"{len(idx)}) of the {len(idx)} bounded features",
             " * outside their training range -> no prediction (NaN) until the next window end; bounds rounded to "
             "float32 */",
             f"#define TCF_N_BOUNDED {len(idx)}",
             f"#define TCF_MAX_OUT {limit}",
             (f"#define TCF_BOUNDED_INIT {{{', '.join(str(j) for j in idx)}}}" if len(idx) < low.size else
              "/* every feature is bounded: feature j has bounds j (no index table, TCF_BOUNDED_INIT) */"),
             f"#define TCF_FEATURE_LOW_INIT {c_float_array(low[idx])}",
             f"#define TCF_FEATURE_HIGH_INIT {c_float_array(high[idx])}"]
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


def check_feature_layout():
    """Refuse to export when the feature channels differ from those ``tcf_features.c`` hard-codes."""
    if tuple(WINDOW_CHANNELS) != _WINDOW_CHANNELS or tuple(LAST_CHANNELS) != _LAST_CHANNELS:
        raise RuntimeError("togglecf.features.windows changed its channels: update togglecf/embedded/tcf_features.c "
                           "(tcf_push_sample) and learned._WINDOW_CHANNELS/_LAST_CHANNELS to match")


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
    window and hop [samples] at the export rate ``fs`` [Hz], and the hashes the generated files
    record."""

    filt: object
    classes: list
    forest: object
    dropped: list
    window: int
    hop: int
    model_hash: str
    gains_hash: str
    schema_hash: str
    fs: float


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
                       schema_hash=meta.get("feature_schema", {}).get("hash", "?"), fs=fs)


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


def load_model_export(model_dir, fs, use_mag: bool, kind: str) -> ModelExport:
    """The checks every learned-filter export makes (``check_export_rate``,
    ``check_feature_layout``), then the filter ``kind`` of ``model_dir`` (``"toggling"``,
    ``"vqf_toggling"``) loaded at ``fs`` [Hz] in 9D (``use_mag``) or 6D, as a ``ModelExport``."""
    model_dir = Path(model_dir)
    meta, fs = check_export_rate(model_dir, fs)
    check_feature_layout()
    try:
        filt = load_toggling_filter(model_dir, fs, use_mag=use_mag, kind=kind)
    except KeyError as e:
        raise ValueError(f"{model_dir / GAINS_FILE}: no {mode_name(kind, use_mag)} gains "
                         f"(add it to [gains] modes and retrain): {e}") from None
    return model_export(model_dir, meta, fs, filt)


def learned_config(ex: ModelExport, model_dir: Path, use_mag: bool, filter_line: str) -> tuple[list, str]:
    """The part of ``tcf_config.h`` every learned filter has: the comment lines (model directory,
    mode, ``filter_line``, classes, the hashes, the trees left out) and the defines
    ``TCF_MODEL_ID``, the models' block (``features_config``), ``TCF_USE_MAG`` and
    ``TCF_CLASS_NAMES_INIT``. Returns (comment lines, defines) for ``framework.config_header``."""
    model_dir = model_dir.resolve()
    filt = ex.filt
    comment = [f"model directory: {model_dir.name}   mode: {'9D (acc + gyr + mag)' if use_mag else '6D (acc + gyr)'}",
               filter_line,
               f"classes (order of the class probabilities): {', '.join(ex.classes)}",
               f"feature schema sha256: {ex.schema_hash}",
               f"model files sha256 (metadata.json model_files): {ex.model_hash}",
               f"gains.json sha256: {ex.gains_hash}",
               f"trees not exported (outputs the filter never uses): {', '.join(ex.dropped) or 'none'}"]
    model_id = c_string(model_dir.name + ':' + ex.model_hash[:12] + ':' + ex.gains_hash[:12])
    names = "{" + ", ".join(c_string(c) for c in ex.classes) + "}"
    body = f"""#define TCF_MODEL_ID {model_id}

{features_config(fs=ex.fs, window=ex.window, hop=ex.hop, feat_params=filt.streaming_features.params,
                 models=filt.models)}
#define TCF_USE_MAG {1 if use_mag else 0}
#define TCF_CLASS_NAMES_INIT {names}
"""
    return comment, body
