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
from togglecf.filters.prediction import PredictionLayout
from togglecf.toggling.gains import GAINS_FILE, mode_name
from togglecf.toggling.load import load_toggling_filter
from togglecf.toggling.inloop import ModelVQFTogglingFilter
from togglecf.toggling.pretrained import load_pretrained, pretrained_settings

__all__ = ["FEATURE_TEMPLATES", "FEATURE_HEADERS", "DEFAULT_MAX_FS", "PORTABLE_DEFAULT_FS", "ModelExport",
           "load_model_export", "load_portable_export", "model_export", "check_model_dir", "check_rate",
           "check_feature_layout", "fallback_config",
           "features_config", "write_forest", "learned_config"]

#: Hz, the largest rate a rate-free export runs at by default (``TCF_MAX_FS``: the feature ring is sized for it)
DEFAULT_MAX_FS = 400.0

#: Hz, the default rate of the harness (``TCF_DEFAULT_FS``) of a portable model's export: the file names no one
#: rate (the pretrained model was trained at several), and the export is rate-free anyway
PORTABLE_DEFAULT_FS = 100.0

#: the models in the loop (streaming features, range check, tree walk) and the prediction row they hold as
#: both filters read it (``tcf_prediction.h``, the C twin of ``filters.prediction``), shipped with every learned filter
FEATURE_TEMPLATES = ("tcf_features.h", "tcf_features.c", "tcf_prediction.h")
#: the headers of FEATURE_TEMPLATES (a firmware build's header list)
FEATURE_HEADERS = ("tcf_features.h", "tcf_prediction.h")
#: the channel layout tcf_filter.c was written for (it hard-codes the ring columns)
_WINDOW_CHANNELS = ("gyr_x", "gyr_y", "gyr_z", "gyr_norm", "acc_x", "acc_y", "acc_z", "acc_norm_dev",
                    "jerk", "mag_norm_dev", "dip_dev")
_LAST_CHANNELS = ("gyr_norm", "acc_x", "acc_y", "acc_z", "acc_norm_dev", "mag_norm_dev", "dip_dev",
                  "acc_hp_x", "acc_hp_y", "acc_hp_z")


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


def _c_double(v) -> str:
    """``v`` as a C double literal that round-trips (Python's repr of a float)."""
    return repr(float(v))


def features_config(*, fset, feat_params, models, max_fs: float) -> str:
    """The ``tcf_config.h`` block of the models in the loop (``tcf_features.c``): the feature
    settings ``fset`` (``FeatureSettings``) in seconds, from which ``tcf_features_init`` derives
    window, hop and EMA gains at the rate it is given; the largest rate ``max_fs`` [Hz] and the
    ring it needs; the rate-free gates of ``feat_params`` (``FeatureCoefficients``), gravity and
    the out-of-range fallback."""
    fallback, _ = fallback_config(models)
    return f"""/* features (togglecf.features.windows.FeatureSettings of the model), in seconds: tcf_features_init(s, fs)
 * derives the per-sample constants at its rate fs [Hz] (L = max(2, round(TCF_WINDOW_S fs)), H = max(1,
 * round(TCF_HOP_S fs)), EMA gains 1 - exp(-1 / (tau fs)); double literals, Python's round) */
#define TCF_WINDOW_S {_c_double(fset.window_s)}      /* s, window length */
#define TCF_HOP_S {_c_double(fset.hop_s)}         /* s, spacing of the window ends (predictions) */
#define TCF_REF_TAU_S {_c_double(fset.ref_tau_s)}     /* s, |m| and dip reference and candidate follow the field */
#define TCF_LP_TAU_S {_c_double(fset.lp_tau_s)}      /* s, acc low-pass behind acc_hp */
#define TCF_REF_NEW_S {_c_double(fset.ref_new_s)}     /* s, rotating time for a new field to become the reference */
/* the largest supported rate: the feature ring holds TCF_WINDOW_MAX = max(2, round(TCF_WINDOW_S TCF_MAX_FS))
 * samples (12 floats each); init refuses a higher rate. Change both by exporting with another max_fs */
#define TCF_MAX_FS {_c_double(max_fs)}        /* Hz */
#define TCF_WINDOW_MAX {window_length(max_fs, fset.window_s)}
#define TCF_REF_NORM_TH {c_float(feat_params.ref_norm_th)}   /* field agrees: ||m| - r| < this * r */
#define TCF_REF_DIP_TH {c_float(feat_params.ref_dip_th)}    /* rad, and |dip - d| < this */
#define TCF_REF_MIN_GYR_SQ {c_float(feat_params.ref_new_min_gyr_sq)}   /* (rad/s)^2: a sample counts as rotating from this |w|^2 */
#define TCF_GRAVITY {c_float(feat_params.gravity)}     /* m/s^2, acc_norm_dev = |a| - g */

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


def check_model_dir(model_dir) -> dict:
    """``model_dir`` is a model directory with ``gains.json``; returns its ``metadata.json``."""
    model_dir = Path(model_dir)
    meta_path = model_dir / "metadata.json"
    if not meta_path.is_file():
        raise FileNotFoundError(f"{meta_path}: not a model directory (run `togglecf train`)")
    gains_path = model_dir / GAINS_FILE
    if not gains_path.is_file():
        raise FileNotFoundError(f"{gains_path}: no learned gains; the C filter needs them "
                                "(`togglecf train` learns them, or gains.save_gains)")
    return json.loads(meta_path.read_text())


def check_rate(fs, what: str = "fs") -> float:
    """``fs`` as a float, refused unless a finite rate > 0 [Hz]."""
    if not (isinstance(fs, (int, float, np.floating)) and math.isfinite(fs) and fs > 0):
        raise ValueError(f"{what} must be a positive sampling rate in Hz, got {fs!r}")
    return float(fs)


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
    max_fs: float = 0.0
    window_max: int = 0


def model_export(model_dir: Path, meta: dict, fs: float, filt, max_fs=None, model_hash: str | None = None,
                 gains_hash: str | None = None) -> ModelExport:
    """The ``ModelExport`` of ``filt`` (loaded from ``model_dir`` at rate ``fs`` [Hz]; ``meta`` its
    ``metadata.json``), the feature ring sized for ``max_fs`` [Hz] (default ``fs``); refuses a
    rate at which the gyro would never be integrated, or ``fs > max_fs``. ``model_hash``,
    ``gains_hash``: the hashes recorded (default: of ``meta``'s model files and of ``gains.json``)."""
    s = filt.settings
    max_fs = fs if max_fs is None else check_rate(max_fs, "max_fs")
    if not 1.0 / fs <= s.max_dt:
        raise ValueError(f"1/fs = {1 / fs:g} s exceeds max_dt = {s.max_dt:g} s: the gyro would never be integrated")
    if fs > max_fs:
        raise ValueError(f"fs = {fs:g} Hz is above max_fs = {max_fs:g} Hz (the largest rate the export supports)")
    classes = list(filt.models.class_names)
    k = len(classes)
    layout = PredictionLayout.of(k)  # the forest's outputs are a prediction row
    out_names = layout.names(classes)
    forest = filt.forest  # the trees the Python filter walks (outputs it never uses dropped)
    kept = {int(g) for g in np.unique(forest.tree_group)}
    dropped = [out_names[i] for i in range(layout.size) if i not in kept]
    fset = filt.models.feature_settings
    L, hop = window_length(fs, fset.window_s), hop_length(fs, fset.hop_s)
    if (L, hop) != (filt.streaming_features.L, filt.hop):
        raise AssertionError("window/hop of the Python filter and the export disagree")
    if model_hash is None:
        model_hash = hashlib.sha256(json.dumps(meta.get("model_files", {}), sort_keys=True).encode()).hexdigest()
    return ModelExport(filt, classes, forest, dropped, L, hop, model_hash=model_hash,
                       gains_hash=gains_hash if gains_hash is not None else file_sha256(model_dir / GAINS_FILE),
                       schema_hash=meta.get("feature_schema", {}).get("hash", "?"), fs=fs, max_fs=max_fs,
                       window_max=window_length(max_fs, fset.window_s))


def write_forest(out_dir: Path, model_dir: Path, ex: ModelExport, layout: str = "array") -> tuple[list, int]:
    """``tcf_forest.h`` / ``tcf_forest.c`` (the trees ``ex.filt`` walks, leaf sums in
    ``TCF_ACC_T`` of ``tcf_config.h``) in ``out_dir``, in the C ``layout`` of ``forest_to_c``:
    returns the paths and the node count (the complete layout's padding included)."""
    comment = (f"model {model_dir.resolve().name}: outputs {', '.join(ex.classes)} (margins), eta_acc xyz, eta_mag xyz"
               + (f"; trees of {', '.join(ex.dropped)} not exported (base margin only)" if ex.dropped else ""))
    header, source = forest_to_c(ex.forest, "tcf_", len(ex.classes), comment, layout=layout)
    files = [atomic_write_text(out_dir / "tcf_forest.h", header),
             atomic_write_text(out_dir / "tcf_forest.c",
                               '#include "tcf_config.h" /* TCF_ACC_T: type of the leaf sums */\n' + source)]
    return files, int(header.split("#define TCF_N_NODES ")[1].split()[0])


def load_model_export(model_dir, fs, use_mag: bool, kind: str, max_fs: float = DEFAULT_MAX_FS) -> ModelExport:
    """The checks every learned-filter export makes (``check_feature_layout``; the model
    directory), then the filter ``kind`` of ``model_dir`` (``"toggling"``, ``"vqf_toggling"``)
    loaded at ``fs`` [Hz] in 9D (``use_mag``) or 6D, as a ``ModelExport``. Rate-free: the C takes
    its rate at init, up to ``max_fs`` [Hz]; ``fs`` is only the harness's default rate (the models'
    ``sampling_rate`` when None)."""
    model_dir = Path(model_dir)
    meta = check_model_dir(model_dir)
    fs = check_rate(fs if fs is not None else meta.get("sampling_rate"))
    check_feature_layout()
    try:
        filt = load_toggling_filter(model_dir, fs, use_mag=use_mag, kind=kind)
    except KeyError as e:
        raise ValueError(f"{model_dir / GAINS_FILE}: no {mode_name(kind, use_mag)} gains "
                         f"(add it to [gains] modes and retrain): {e}") from None
    return model_export(model_dir, meta, fs, filt, max_fs)


def load_portable_export(path, fs, use_mag: bool, max_fs: float) -> ModelExport:
    """``load_model_export`` of a portable model file (``learn.portable``: the pretrained learned VQF the
    package ships, or ``togglecf train --from-pretrained``'s): its learned VQF with the models in the loop
    (``ModelVQFTogglingFilter``, what ``LearnedVQF`` runs unless learning is off) in 9D or 6D, rate-free
    (``max_fs`` [Hz]); ``fs`` only the harness's default rate (None: ``PORTABLE_DEFAULT_FS``).
    The file holds models and settings: its sha256 is recorded as both hashes."""
    path = Path(path)
    pm = load_pretrained(path)  # a bad file: refused with what it is
    mode = mode_name("vqf_toggling", use_mag)
    if mode not in pm.gains:
        raise ValueError(f"{path}: no {mode} settings in this model file (has {', '.join(sorted(pm.gains))})")
    fs = check_rate(fs if fs is not None else PORTABLE_DEFAULT_FS)
    check_feature_layout()
    digest = file_sha256(path)
    filt = ModelVQFTogglingFilter(fs, pretrained_settings(use_mag, path), models=pm.models, use_mag=use_mag)
    return model_export(path, {"feature_schema": {"hash": pm.models.schema_hash}}, fs, filt, max_fs,
                        model_hash=digest, gains_hash=digest)


def learned_config(ex: ModelExport, model_dir: Path, use_mag: bool, filter_line: str) -> tuple[list, str]:
    """The part of ``tcf_config.h`` every learned filter has: the comment lines (model directory,
    mode, ``filter_line``, classes, the hashes, the trees left out) and the defines
    ``TCF_MODEL_ID``, the models' block (``features_config``), ``TCF_USE_MAG`` and
    ``TCF_CLASS_NAMES_INIT``. Returns (comment lines, defines) for ``framework.config_header``."""
    model_dir = model_dir.resolve()
    filt = ex.filt
    what = "model file" if model_dir.is_file() else "model directory"
    comment = [f"{what}: {model_dir.name}   mode: {'9D (acc + gyr + mag)' if use_mag else '6D (acc + gyr)'}",
               filter_line,
               f"classes (order of the class probabilities): {', '.join(ex.classes)}",
               f"feature schema sha256: {ex.schema_hash}",
               f"model sha256 ({'the model file' if model_dir.is_file() else 'metadata.json model_files'}): {ex.model_hash}",
               f"gains sha256 ({'the model file' if model_dir.is_file() else 'gains.json'}): {ex.gains_hash}",
               f"trees not exported (outputs the filter never uses): {', '.join(ex.dropped) or 'none'}"]
    model_id = c_string(model_dir.name + ':' + ex.model_hash[:12] + ':' + ex.gains_hash[:12])
    names = "{" + ", ".join(c_string(c) for c in ex.classes) + "}"
    body = f"""#define TCF_MODEL_ID {model_id}

{features_config(fset=filt.models.feature_settings, feat_params=filt.streaming_features.params,
                 models=filt.models, max_fs=ex.max_fs)}
#define TCF_USE_MAG {1 if use_mag else 0}
#define TCF_CLASS_NAMES_INIT {names}
"""
    return comment, body
