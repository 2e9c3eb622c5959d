"""The toggling filter as a self-contained C99 source set.

``export_c_filter(model_dir, out_dir, fs=None, use_mag=True, max_fs=400)`` writes into ``out_dir``
(e.g. ``build/embedded/NAME/filter/``) a rate-free filter, as the learned VQF's export
(``cvqf_toggling``): ``tcf_filter_init(&f, fs)`` takes the rate (up to ``TCF_MAX_FS``) and derives
every per-sample gain and the features' window and hop from it and the settings in seconds;
``tcf_filter_update_dt`` takes the per-sample Δt of the gyro integration:

* ``tcf_filter.h`` / ``tcf_filter.c``: hand-written port of ``toggling.inloop.toggling_inloop_batch`` (one sample)
  (streaming features, trees every hop, softmax, toggling step 1-7), float32, no heap, all
  state in one fixed-size ``tcf_filter_t`` (templates shipped in ``togglecf/embedded/``, with the
  shared ``tcf_features.{h,c}`` and ``tcf_prediction.h``);
* ``tcf_config.h``: generated: the feature settings in seconds, ``TCF_MAX_FS`` and the ring size
  ``TCF_WINDOW_MAX``, the harness's default rate ``TCF_DEFAULT_FS``, the learned time constants of
  ``gains.json`` (9D or 6D) in seconds (``tcf_filter_init`` turns them into per-sample gains
  k = 1 − exp(−Ts/τ) at its rate, the Python filter's coefficients at that rate), class names and
  the hashes of the model files it came from;
* ``tcf_forest.h`` / ``tcf_forest.c``: the merged forest (``export.forest_to_c``, outputs
  S class margins, η_a xyz, η_m xyz) without the trees the filter never uses (the outputs
  ``ModelTogglingFilter`` drops: η_a at noise weight 0; η_m in 6D, or at noise weight 0 without
  disturbance scaling). Leaf sums in float (``TCF_ACC_T``, set in ``tcf_config.h``);
* ``tcf_harness.c`` + ``Makefile``: a host program ``tcf_harness [--fs HZ] in.csv out.csv`` (CSV of
  gyr, acc[, mag][, dt] in rad/s, m/s², µT, s -> w,x,y,z), used by the tests to compare with Python;
* ``filter_report.json``: the returned report (files, state size, sizes).

``build_harness(out_dir)`` compiles the harness with gcc; ``run_harness(exe, gyr, acc, mag)``
runs it on arrays and returns the quaternions ``(N, 4)``.
"""
from __future__ import annotations

import tempfile
from dataclasses import asdict
from pathlib import Path

import numpy as np

from togglecf.core.io import atomic_write_json
from togglecf.embedded import framework, learned
from togglecf.embedded.framework import HARNESS_CFLAGS
from togglecf.embedded.forest_export import c_layout_bytes
from togglecf.embedded.toolchain import (
    c_float,
    link_riscv,
    run_harness_command,
    run_prediction_harness,
    write_imu_csv,
)

__all__ = ["export_c_filter", "build_harness", "run_harness", "harness_features", "TEMPLATES", "FILTER_SOURCES",
           "C_FILTER", "HARNESS_CFLAGS", "state_bytes_formula"]

TEMPLATES = ("tcf_filter.h", "tcf_filter.c", *learned.FEATURE_TEMPLATES, "tcf_math.h", "tcf_harness.c", "tcf_csv.h")
FILTER_SOURCES = ("tcf_filter.c", "tcf_features.c", "tcf_forest.c")
#: the toggling CF as C files (framework.CSourceSet)
C_FILTER = framework.CSourceSet(
    what="the exported toggling filter", exporter="export_c_filter", api_header="tcf_filter.h",
    state_type="tcf_filter_t", sources=FILTER_SOURCES,
    headers=("tcf_filter.h", *learned.FEATURE_HEADERS, "tcf_math.h", "tcf_forest.h", "tcf_config.h"), templates=TEMPLATES,
    generated=("tcf_config.h", "tcf_forest.h", "tcf_forest.c"), harness="tcf_harness",
    firmware=framework.FirmwareCalls(setup="if (tcf_filter_init(&tcf_f, (float)TCF_DEFAULT_FS) != 0) return 1;",
                                     update="tcf_filter_update(&tcf_f, g, a, m);",
                                     quat="tcf_filter_quat(&tcf_f, tcf_q);"))


def state_bytes_formula(window_max: int, n_classes: int) -> int:
    """``sizeof(tcf_filter_t)`` as documented in ``tcf_filter.h``: 4-byte members only,
    ``4 · (69 + 12 L_max + 3 S)`` (69 = the per-sample constants of the init rate Ts, fallback gains
    2, γ, bias gain, tan of the heading's largest turn, the field reference's gain 7; quaternion 4, bias 3,
    a_pred 3, m_pred 3, the field reference's norm and dip 2, flag 1, the features' per-sample
    constants 6, EMA references as hi + lo 10, candidate field as hi + lo 4 and its count 1,
    previous acc 3, last-sample features 10, counters 3, η̂ 6, diagnostics 3; 12 L_max the ring,
    ``TCF_WINDOW_MAX`` rows for ``TCF_MAX_FS``; 3 S the per-state gains α_acc, α_mag and the class
    probabilities)."""
    return 4 * (69 + 12 * int(window_max) + 3 * int(n_classes))


def _filter_defines(settings, static_index: int, fs: float) -> str:
    """The toggling CF's own lines of ``tcf_config.h``: the harness's default rate ``fs`` [Hz],
    the step size limit, the learned time constants in seconds (``tcf_filter_init`` turns them into
    per-sample gains at its rate), bias learning, disturbance scaling, noise weights and the
    confidence floor."""
    s = settings
    return f"""/* the rate is set at init, tcf_filter_init(&f, fs); the host harness's and the size probes' default */
#define TCF_DEFAULT_FS {c_float(fs)}   /* Hz */
#define TCF_MAX_DT {c_float(s.max_dt)}   /* s, longest step still integrated */

/* learned time constants (gains.json) [s], per class in the order above; tcf_filter_init derives the
 * per-sample gains k = 1 - exp(-Ts / tau) at its rate (Ts = 1/fs; tau 0: k = 1, tau < 0: k = 0, off) */
#define TCF_TAU_ACC_INIT {framework.c_float_array(s.tau_acc)}
#define TCF_TAU_MAG_INIT {framework.c_float_array(s.tau_mag)}
#define TCF_OUTPUT_TAU {c_float(s.output_tau)}   /* s, output blend gamma */
#define TCF_BIAS_TAU {c_float(s.bias_tau)}   /* s, gyro bias learning at rest */
#define TCF_BIAS_GATE {c_float(s.bias_gate)}       /* rad/s */
#define TCF_STATIC_INDEX {static_index}     /* class in which the gyro bias is learned: {s.static_state} */
#define TCF_MAG_DISTURBANCE_SCALE {c_float(s.mag_disturbance_scale)}   /* uT, 0 = off */
#define TCF_MAG_REJECTION_FACTOR {c_float(s.mag_rejection_factor)}   /* largest divisor of the mag gain by the back-off */
#define TCF_MAG_RATE_LIMIT {c_float(s.mag_rate_limit)}   /* rad/s, fastest turn of m_pred by the heading correction (0: none) */
/* step 5b, the heading bias in motion: 1 / heading_bias_tau (0: off), fed where the field passes the check against
 * its reference (which follows it with TCF_MAG_REF_TAU) and |a| is within TCF_ACC_NORM_THRESHOLD g of TCF_GRAVITY */
#define TCF_HEADING_BIAS_RATE {c_float(1.0 / s.heading_bias_tau if s.heading_bias_tau > 0.0 else 0.0)}   /* 1/s */
#define TCF_HEADING_BIAS_CLIP {c_float(s.heading_bias_clip)}   /* rad/s, the feed never takes |bias| above it */
#define TCF_MAG_NORM_THRESHOLD {c_float(s.mag_norm_threshold)}   /* relative deviation of |m| from the reference */
#define TCF_MAG_DIP_THRESHOLD {c_float(s.mag_dip_threshold)}   /* rad, deviation of the dip from the reference */
#define TCF_MAG_REF_TAU {c_float(s.mag_ref_tau)}   /* s */
#define TCF_ACC_NORM_THRESHOLD {c_float(s.acc_norm_threshold)}   /* relative deviation of |a| from g */
#define TCF_NOISE_WEIGHT_ACC {c_float(s.noise_weight_acc)}
#define TCF_NOISE_WEIGHT_MAG {c_float(s.noise_weight_mag)}
/* the fallback (no prediction, or top probability below TCF_CONFIDENCE_FLOOR of the sum): the cautious
 * gains, per sensor the smallest of the per-class ones (tcf_filter_init) */
#define TCF_CONFIDENCE_FLOOR {c_float(s.confidence_floor)}
"""


def export_c_filter(model_dir, out_dir, fs=None, use_mag: bool = True, riscv: bool = True, *,
                    max_fs: float = learned.DEFAULT_MAX_FS, forest_layout: str = "array") -> dict:
    """Write the C filter of ``model_dir`` (a ``togglecf train`` directory with ``gains.json``)
    into ``out_dir``, rate-free: the C takes its rate at init (``tcf_filter_init(&f, fs)``, any rate
    up to ``max_fs`` [Hz], ``TCF_MAX_FS``, for which the feature ring is sized). ``fs`` [Hz]: only
    the default rate of the host harness and the size probes (``TCF_DEFAULT_FS``; None: the models'
    ``sampling_rate``); the report's ``window``, ``hop`` and ``per_sample_gains`` are at it. Returns
    the report (also written as ``out_dir/filter_report.json``). ``forest_layout``: the trees' C layout
    (``forest_export.forest_to_c``: ``array``, the faster on a microcontroller, or ``complete``, the faster
    on a processor that predicts branches). The report: ``files``, ``state_bytes``
    (sizeof(tcf_filter_t), measured with gcc), ``object_sizes`` and, with the RISC-V toolchain,
    ``linked_riscv`` (an rv32imc picolibc program calling init/update: its ``flash`` = text + data
    bytes)."""
    model_dir, out_dir = Path(model_dir), Path(out_dir)
    ex = learned.load_model_export(model_dir, fs, use_mag, kind="toggling", max_fs=max_fs)
    filt, s, L, k = ex.filt, ex.filt.settings, ex.window_max, len(ex.classes)
    comment, common = learned.learned_config(ex, model_dir, use_mag,
                                             f"filter: the toggling CF (gains.json, {'9d' if use_mag else '6d'})")
    config = framework.config_header("tcf_config.h", "cfilter.export_c_filter", comment, common + "\n"
                                     + _filter_defines(s, s.states.index(s.static_state), ex.fs))
    files = framework.write_source_set(out_dir, C_FILTER, {"tcf_config.h": config})
    forest_files, n_nodes = learned.write_forest(out_dir, model_dir, ex, forest_layout)
    files += forest_files
    p = filt.params
    report = {"out_dir": str(out_dir), "model_dir": str(model_dir), "files": [str(f) for f in files],
              "fs": ex.fs, "rate": "at init (tcf_filter_init); fs: the harness's default", "max_fs": ex.max_fs,
              "window_max": L, "use_mag": bool(use_mag), "window": ex.window, "hop": ex.hop, "n_classes": k,
              "class_names": ex.classes, "n_features": int(ex.forest.n_features), "n_trees": int(len(ex.forest.roots)),
              "n_nodes": n_nodes, "forest_layout": forest_layout,
              "forest_layout_bytes": c_layout_bytes(ex.forest), "dropped_outputs": ex.dropped, "settings": asdict(s),
              "per_sample_gains": {"alpha_acc": p.alpha_acc.tolist(), "alpha_mag": p.alpha_mag.tolist(),
                                   "gamma": float(p.gamma), "bias_gain": float(p.bias_gain),
                                   "alpha_fallback_acc": float(p.alpha_fallback_acc),
                                   "alpha_fallback_mag": float(p.alpha_fallback_mag),
                                   "tan_mag_step": float(p.tan_mag_step)},
              "schema_hash": ex.schema_hash, "model_hash": ex.model_hash, "gains_sha256": ex.gains_hash,
              "fallback": learned.fallback_config(filt.models)[1],
              "state_bytes_formula": "4 * (69 + 12 * window_max + 3 * n_classes)",
              "state_bytes_documented": state_bytes_formula(L, k)}
    size, documented = framework.probe_sizes(out_dir, "tcf_filter.h", ["sizeof(tcf_filter_t)", "TCF_STATE_BYTES"])
    if documented != report["state_bytes_documented"]:
        raise AssertionError(f"TCF_STATE_BYTES {documented} != state_bytes_formula {report['state_bytes_documented']}")
    report["state_bytes"] = size
    report["object_sizes"] = framework.per_source_sizes(out_dir, C_FILTER, riscv=riscv, arm=False)
    report["linked_riscv"] = (link_riscv([out_dir / f for f in FILTER_SOURCES], [out_dir],
                                         framework.firmware_main(C_FILTER)) if riscv else None)
    atomic_write_json(out_dir / "filter_report.json", report)
    return report


def build_harness(out_dir, exe=None, cflags=HARNESS_CFLAGS) -> Path:
    """Compile ``tcf_harness`` from the sources in ``out_dir`` with the host gcc; returns the
    executable (default ``out_dir/tcf_harness``). Raises ``RuntimeError`` with gcc's output."""
    return framework.build_host_harness(out_dir, C_FILTER, exe, cflags)


def run_harness(exe, gyr, acc, mag=None, *, diagnostics: bool = False, no_mag: bool = False, predictions=None,
                fs=None, dt=None):
    """Run the compiled harness on ``(N, 3)`` arrays (``mag=None``: a 6-column CSV, the filter
    gets ``mag = NULL``; ``no_mag``: pass NULL although mag is given). Returns the quaternions
    ``(N, 4)`` float64, or with ``diagnostics`` ``(quat, dict)`` with the held predictions
    (``p_<class>``, ``eta_acc_x`` ...), ``alpha_acc``, ``alpha_mag`` per sample and the filter's
    ``ns_per_sample`` (the harness's clock() timing of the update calls).
    ``predictions (N, S + 6)``: drive the toggling step with these instead of the trees
    (``tcf_filter_update_pred``; as ``TogglingFilter.update_batch(..., predictions=...)``).
    ``fs`` [Hz]: the rate given to ``tcf_filter_init`` (default ``TCF_DEFAULT_FS``); ``dt`` [s] (scalar
    or ``(N,)``): the per-sample time steps (``tcf_filter_update_dt``; as ``update_batch(..., dt=...)``)."""
    return run_prediction_harness(exe, gyr, acc, mag, diagnostics=diagnostics, no_mag=no_mag,
                                  predictions=predictions, fs=fs, dt=dt)


def harness_features(exe, gyr, acc, mag=None):
    """The C filter's feature rows at its window ends: ``(ends (n,), X (n, F))`` float64, to
    compare with ``features.compute_features`` (``tcf_harness --features``)."""
    with tempfile.TemporaryDirectory() as tmp:
        fin, fout, ffeat = Path(tmp) / "in.csv", Path(tmp) / "out.csv", Path(tmp) / "feat.csv"
        write_imu_csv(fin, gyr, acc, mag)
        run_harness_command(exe, [str(exe), "--features", str(ffeat), str(fin), str(fout)])
        F = np.loadtxt(ffeat, delimiter=",", ndmin=2)
    return F[:, 0].astype(np.int64), F[:, 1:]
