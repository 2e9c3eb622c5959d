"""The C99 toggling filter (``togglecf.embedded.cfilter``, ``togglecf/embedded/``): its float32 quaternions,
features and held predictions equal the Python (float64) in-loop filter on a real trial in 9D
and 6D, bad samples do not poison its state, the harness reads CSV robustly, the state size is
the documented formula, the sources compile warning-free for the host and for rv32imc.

Tolerances (measured on all 25 BROAD trials, 9D and 6D, with the models `make run` trains on all of
them, ``build/transfer/models_broad``: an in-sample equivalence check, out-of-range and
low-confidence fallback included; last re-measured with feature version 3, models of the run at
``9f8c6ed``, C of ``42727cf``):

* Filter arithmetic alone (the C toggling step driven by Python's predictions vs
  ``TogglingFilter`` in float64): at most 0.0063° (9D, trial 21) / 0.0103° (6D, trial 28, heading
  from the gyro only) over all samples of all trials. Asserted: max <= 0.01° on the mini cut below
  (so the full-length 6D trial 28 would exceed the bound by 0.0003°).
* The whole in-loop filter (features, range check, trees and step in float32): a feature that
  lands within float32 rounding of a split threshold or of its training-range bound decides the
  other way for that hop; the held prediction then differs for one hop and so do the gains for
  those samples. Median of the per-trial maxima 0.0066° (9D) / 0.0036° (6D); 9D <= 0.033° on every
  trial but 36: 0.079°; 6D <= 0.0095° on every trial but 18: 0.024°. (With feature version 1, trial
  32, magnet attached at 1 cm, reached 0.65°: flips moved the heading while the magnetometer was
  disturbed.) This is the model's own sensitivity, not an error of the port. Asserted here on trial
  05 (the issue's test), with the tiny test model: max over all samples <= 0.05°.
* Held predictions: within 1e-4 (abs) + 1e-4 (rel) at >= 97 % of the samples (the flips above
  are the exceptions; measured >= 97.7 % on every one of the 25 trials).
* Features: within 1e-3 (rel) + 1e-4 (abs) of ``compute_features`` (measured on the whole of
  trial 15 with feature version 3: the jerk features differ most, by <= 2.2e-3 abs on values of
  hundreds of m/s³, all others by <= 9e-6 abs; the *_dev features of the field reference by
  <= 7e-6, thanks to the compensated EMA of tcf_features.c; <= 1.7e-5 on the magnet trials 29 and 32).

* Rate at init (issue 25): one export (default rate, the models' 285.714 Hz) run with
  ``tcf_filter_init(&f, fs)`` at 100 Hz on the phone trial ``conftest.RATE_PHONE_TRIAL`` (tyrex_nexus5, real 100 Hz)
  and at 200 Hz on BROAD trial 05 linearly resampled to 200 Hz, against the Python filter built at
  that rate: the bounds above, unchanged (the arithmetic with C's own predictions <= 0.01°, the
  in-loop filter <= 0.05° with >= 97 % of the samples holding the same prediction, a window's
  range check falling back in one and not the other, as above, at <= 3 % of them), because the
  rate enters C and Python only through the gains and the window/hop, computed from the same
  seconds (C: float32 ``-expm1f(-Ts/tau)`` at init; Python: float64 ``1 - exp(-Ts/tau)``, a
  relative difference of float32 rounding). Measured values: printed by the test (``-s``).

Data: the models are the tiny test models trained on the shipped mini BROAD cuts of 02 and 07
(``base_model_dir``), so every test here runs without ../shared. The port's equivalence is checked
on the 4000-sample mini cut of trial 24 (rest, rotation, linear acceleration, taps; not trained
on) always, and, as the real-data claim above, on the full trial 05 (~53000 samples with breaks)
when BROAD is present (the ``broad05`` parameter of ``cf_trial``).
"""
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest

from conftest import train_tiny_models, with_fixed_gains
from togglecf.core.quaternion import angle_between
from togglecf.data.broad import DatasetIndex
from togglecf.embedded import cfilter, framework, toolchain
from togglecf.embedded.toolchain import c_float
from togglecf.features.windows import window_length
from togglecf.filters.timeconst import gain

if shutil.which("gcc") is None:
    pytest.skip("gcc not installed: the C filter cannot be compiled", allow_module_level=True)

ANGLE_TOL_DEG = 0.05
#: the filter arithmetic alone (C driven by given predictions vs TogglingFilter) [deg] (module docstring)
ARITH_TOL_DEG = 0.01
#: the 100 Hz phone trial of the rate test (tyrex_nexus5 beside BROAD; the learned VQF's rate test uses it too)
WARN_FLAGS = ["-std=c99", "-Wall", "-Wextra", "-pedantic", "-Wdouble-promotion", "-Wshadow"]


def _gains(class_names, static_state, use_mag):
    from togglecf.filters.toggling import TogglingSettings

    s = len(class_names)
    # time constants [s]; per sample at 285.714 Hz (0.002, 0.0005, 0.0003, 0.0001, 0.0002, 0.0004) and
    # (0.0005, 0.0002, 0.0001, 0.0003, 0.0002, 0.0001); γ 0.6 / 1, bias gain 0.001 / 0.003
    base_a = (1.748, 6.998, 11.66, 35.0, 17.5, 8.748)
    base_m = (6.998, 17.5, 35.0, 11.66, 17.5, 35.0)
    if use_mag:  # exercises every step: η_a trees dropped (weight 0), η_m half-weighted, σ_m on and bounded
        # (the back-off at most 1.5: capped for |η̂_m| above 7.1 µT), γ < 1, the heading correction's rate bound
        extra = dict(output_tau=0.00382, bias_tau=3.498, bias_gate=0.05, mag_disturbance_scale=10.0,
                     mag_rejection_factor=1.5, noise_weight_acc=0.0, noise_weight_mag=0.5, mag_rate_limit=0.02)
    else:
        # and a confidence floor: low-confidence windows run the core (12.5 s, no bias, no noise removal)
        extra = dict(output_tau=0.0, bias_tau=1.165, bias_gate=0.05, mag_disturbance_scale=0.0, noise_weight_acc=0.5,
                     noise_weight_mag=1.0, confidence_floor=0.8)
    return TogglingSettings(states=tuple(class_names), static_state=static_state, tau_acc=base_a[:s],
                            tau_mag=base_m[:s], **extra)


@pytest.fixture(scope="module")
def base_model_dir(mini_index, tmp_path_factory):
    """The tiny models (``conftest.train_tiny_models``), trained on the mini cuts of 02 and 07
    only, so that the mini cut of 24 the port is checked on is unseen, as trial 05 is. On its own
    training windows a tiny model's split thresholds are the windows' own feature values (64 bins
    over ~270 windows; window min/max features are sample values whatever the hop phase), so the
    float32 C features often land on the other side of a threshold there, and the held predictions
    of C and Python differ far more often on training cuts than on an unseen trial."""
    return train_tiny_models(mini_index.root, "02,07", tmp_path_factory.mktemp("cf_base") / "tiny")


@pytest.fixture(scope="module")
def model_dir(base_model_dir, tmp_path_factory):
    """A copy of the tiny model directory with fixed (not learned) 9D and 6D gains."""
    d = tmp_path_factory.mktemp("cf_models") / "tiny"
    shutil.copytree(base_model_dir, d)
    return with_fixed_gains(d, _gains)


@pytest.fixture(scope="module")
def exported(model_dir, mini_trial, tmp_path_factory):
    """mode -> (report, harness executable), for BROAD's rate (the same in every trial)."""
    out = {}
    for mode in ("9d", "6d"):
        d = tmp_path_factory.mktemp(f"cf_{mode}")
        rep = cfilter.export_c_filter(model_dir, d, mini_trial.fs, use_mag=mode == "9d")
        out[mode] = (rep, cfilter.build_harness(d))
    return out


@pytest.fixture(params=["mini", pytest.param("broad05", marks=pytest.mark.broad)])
def cf_trial(request, exported):
    """The trial the C/Python equivalence is checked on: the mini cut of trial 24 (always), the
    full trial 05 (``broad``; skipped without BROAD)."""
    t = request.getfixturevalue("mini_trial" if request.param == "mini" else "broad_trial")
    assert t.fs == exported["9d"][0]["fs"]  # the filter was exported for this rate
    return t


def _python(model_dir, trial, use_mag, gyr=None, acc=None, mag=None):
    from togglecf.toggling import load_toggling_filter

    f = load_toggling_filter(model_dir, trial.fs, use_mag=use_mag)
    gyr = trial.gyr if gyr is None else gyr
    acc = trial.acc if acc is None else acc
    mag = (trial.mag if mag is None else mag) if use_mag else None
    return f.update_batch(gyr, acc, mag)


def _angles_deg(qa, qb):
    return np.degrees(angle_between(qa, qb))


# --------------------------------------------------------------------------------- equivalence

def test_c_quaternions_match_python_9d(exported, model_dir, cf_trial):
    _, exe = exported["9d"]
    py = _python(model_dir, cf_trial, True)
    qc = cfilter.run_harness(exe, cf_trial.gyr, cf_trial.acc, cf_trial.mag)
    assert qc.shape == py.quat.shape
    ang = _angles_deg(qc, py.quat)
    assert np.all(np.isfinite(ang))
    assert ang.max() <= ANGLE_TOL_DEG, f"max {ang.max():.4f}°, 99.9th percentile {np.percentile(ang, 99.9):.4f}°"


def test_c_filter_arithmetic_matches_python_with_the_same_predictions(exported, model_dir, cf_trial):
    """The toggling step alone (tcf_filter_update_pred) vs TogglingFilter, both driven by the
    Python in-loop filter's predictions: float32 vs float64 rounding only, no branch flips."""
    from togglecf.filters.toggling import TogglingFilter
    from togglecf.toggling import load_toggling_filter

    for mode in ("9d", "6d"):
        rep, exe = exported[mode]
        use_mag = mode == "9d"
        f = load_toggling_filter(model_dir, cf_trial.fs, use_mag=use_mag)
        mag = cf_trial.mag if use_mag else None
        py = f.update_batch(cf_trial.gyr, cf_trial.acc, mag)
        names = [f"p_{c}" for c in rep["class_names"]] + [f"eta_{t}_{ax}" for t in ("acc", "mag") for ax in "xyz"]
        P = np.stack([py.diagnostics[k] for k in names], axis=1)
        ref = TogglingFilter(cf_trial.fs, f.settings, use_mag=use_mag).update_batch(
            cf_trial.gyr, cf_trial.acc, mag, predictions=P).quat
        assert np.array_equal(ref, py.quat)  # the same thing in Python
        if not use_mag:  # the 6D gains have a confidence floor: both branches of step 4 are exercised
            low = py.diagnostics["p_static"] == 0.0  # fallback: no bias update (p_static 0), cautious gain
            assert 0.0 < low.mean() < 1.0, f"6D: {low.mean():.3f} of the samples fall back"
        qc = cfilter.run_harness(exe, cf_trial.gyr, cf_trial.acc, mag, predictions=P)
        ang = _angles_deg(qc, ref)
        assert ang.max() <= ARITH_TOL_DEG, f"{mode}: max {ang.max():.5f}°"


def test_c_features_match_compute_features(exported, model_dir, mini_trial):
    from togglecf.features.windows import compute_features
    from togglecf.learn.compiled import CompiledModels
    from togglecf.learn.models import load_bundle

    settings = CompiledModels.from_bundle(load_bundle(model_dir)).feature_settings
    _, exe = exported["9d"]
    t = mini_trial  # 4000 samples (was 0:20000 of trial 05; the bad samples below moved with it)
    ends_c, Xc = cfilter.harness_features(exe, t.gyr, t.acc, t.mag)
    X, ends = compute_features(t.gyr, t.acc, t.mag, t.fs, settings)
    assert np.array_equal(ends_c, ends)  # the same window ends (first full window, then every hop)
    np.testing.assert_allclose(Xc, X, rtol=1e-3, atol=1e-4)
    # bad samples, the first one included: the references start at the first finite sample, a
    # window holding a bad value gives missing stats of that channel, as compute_features
    gyr, acc, mag = t.gyr.copy(), t.acc.copy(), t.mag.copy()
    acc[0], mag[:3] = np.nan, np.nan
    acc[1000], mag[2000], gyr[3000] = np.inf, np.nan, np.nan  # in the rest, and twice in the movement
    ends_c, Xc = cfilter.harness_features(exe, gyr, acc, mag)
    X, ends = compute_features(gyr, acc, mag, t.fs, settings)
    np.testing.assert_array_equal(np.isnan(Xc), np.isnan(X))
    np.testing.assert_allclose(Xc, X, rtol=1e-3, atol=1e-4)
    assert np.isfinite(X[ends > 3100]).all()


def test_c_field_reference_matches_python_through_a_new_field(exported, model_dir, mini_trial):
    """The gated field reference (features v3) in C: a sensor turning at 30 °/s whose field is 20 %
    stronger from 5 s to 40 s, a NaN and a zero-norm sample among it. Every branch is taken (the
    stronger field is a disturbance for ref_new_s = 20 s, then the reference; the old field is a
    disturbance in turn), and the C features follow compute_features with the tolerances above."""
    from togglecf.features.windows import compute_features, feature_schema
    from togglecf.learn.compiled import CompiledModels
    from togglecf.learn.models import load_bundle

    settings = CompiledModels.from_bundle(load_bundle(model_dir)).feature_settings
    _, exe = exported["9d"]
    fs = mini_trial.fs
    t = np.arange(int(50.0 * fs)) / fs
    w = np.radians(30.0)
    gyr = np.zeros((t.size, 3))
    gyr[:, 2] = w
    acc = np.tile([0.0, 0.0, 9.81], (t.size, 1))
    mag = np.stack([25.0 * np.sin(w * t), 25.0 * np.cos(w * t), np.full(t.size, -43.3)], axis=1)
    mag[(t >= 5.0) & (t < 40.0)] *= 1.2
    mag[int(7.0 * fs)] = np.nan
    mag[int(8.0 * fs)] = 0.0
    ends_c, Xc = cfilter.harness_features(exe, gyr, acc, mag)
    X, ends = compute_features(gyr, acc, mag, fs, settings)
    assert np.array_equal(ends_c, ends)
    np.testing.assert_array_equal(np.isnan(Xc), np.isnan(X))
    np.testing.assert_allclose(Xc, X, rtol=1e-3, atol=1e-4)
    dev = X[:, feature_schema(settings).names.index("mag_norm_dev_last")]
    te = ends / fs
    assert np.all(np.abs(dev[(te > 10.0) & (te < 24.0)] - 10.0) < 0.01)  # held: the disturbance shows
    assert np.all(np.abs(dev[(te > 27.0) & (te < 40.0)]) < 0.01)  # taken as the new field
    assert np.all(np.abs(dev[te > 41.0] + 10.0) < 0.01)  # the old field is now the disturbance


def test_c_held_predictions_match_python(exported, model_dir, cf_trial):
    rep, exe = exported["9d"]
    py = _python(model_dir, cf_trial, True)
    _, diag = cfilter.run_harness(exe, cf_trial.gyr, cf_trial.acc, cf_trial.mag, diagnostics=True)
    kept = [f"p_{c}" for c in rep["class_names"]] + [n for n in ("eta_acc_x", "eta_acc_y", "eta_acc_z", "eta_mag_x",
                                                                  "eta_mag_y", "eta_mag_z")
                                                      if n not in rep["dropped_outputs"]]
    assert "eta_acc_x" in rep["dropped_outputs"] and "eta_mag_x" in kept  # w_a = 0: those trees are not exported
    P = np.stack([py.diagnostics[k] for k in kept], axis=1)
    C = np.stack([diag[k] for k in kept], axis=1)
    # the same samples have no prediction (NaN until the first full window, and where a window is out of
    # the models' training range: the fallback, learn.ranges)
    assert np.array_equal(np.isnan(P[:, 0]), np.isnan(C[:, 0]))
    assert np.array_equal(py.diagnostics["fallback"], diag["fallback"])
    ok = ~np.isnan(P[:, 0])
    # before the first full window, and at fallback windows only (this was "> 99 % of the samples",
    # which holds on a full trial but not on 4000 samples, where the first window is 1.4 %)
    first = int(np.argmax(ok | (py.diagnostics["fallback"] == 1.0)))
    assert 0 < first < rep["window"] and np.all(ok[first:] | (py.diagnostics["fallback"][first:] == 1.0))
    close = np.all(np.abs(C[ok] - P[ok]) <= 1e-4 + 1e-4 * np.abs(P[ok]), axis=1)
    assert close.mean() >= 0.97, f"only {close.mean():.3%} of the samples hold the same prediction"
    np.testing.assert_allclose(C[ok, :len(rep["class_names"])].sum(axis=1), 1.0, atol=1e-5)
    assert np.all(np.isfinite(diag["alpha_acc"])) and diag["ns_per_sample"] > 0


def test_c_6d_matches_python_6d(exported, model_dir, cf_trial):
    rep, exe = exported["6d"]
    assert {"eta_mag_x", "eta_mag_y", "eta_mag_z"} <= set(rep["dropped_outputs"])  # unused in 6D
    py = _python(model_dir, cf_trial, False)  # Python 6D: mag None (zeros in the features)
    qc = cfilter.run_harness(exe, cf_trial.gyr, cf_trial.acc, None)  # 6-column CSV: mag = NULL
    ang = _angles_deg(qc, py.quat)
    assert ang.max() <= ANGLE_TOL_DEG, f"max {ang.max():.4f}°"
    # --no-mag on a 9-column file is the same
    qn = cfilter.run_harness(exe, cf_trial.gyr, cf_trial.acc, cf_trial.mag, no_mag=True)
    assert np.array_equal(qn, qc)


def test_bad_samples_do_not_poison_the_c_state(exported, model_dir, mini_trial):
    t = mini_trial  # 4000 samples (was 0:6000 of trial 05): every index below is inside it
    gyr, acc, mag = t.gyr.copy(), t.acc.copy(), t.mag.copy()
    gyr[0] = np.nan  # a bad first sample (before initialisation)
    gyr[100:105] = np.nan
    gyr[200, 1] = np.inf
    gyr[300] = [40.0, 0.0, 0.0]  # saturated
    acc[1000:1010] = np.nan
    acc[1500] = 0.0
    acc[1600, 2] = np.inf
    mag[2000:2060] = np.nan  # longer than a window: NaN features for a whole hop
    mag[2500] = 0.0
    mag[2600, 0] = -np.inf
    gyr[3000], acc[3000], mag[3000] = np.nan, np.nan, np.nan
    for mode, m in (("9d", mag), ("6d", None)):
        _, exe = exported[mode]
        qc = cfilter.run_harness(exe, gyr, acc, m)
        assert np.all(np.isfinite(qc)), mode
        np.testing.assert_allclose(np.linalg.norm(qc, axis=1), 1.0, atol=1e-6)
        py = _python(model_dir, t, mode == "9d", gyr, acc, mag)  # the same policy as Python
        ang = _angles_deg(qc, py.quat)
        assert ang.max() <= ANGLE_TOL_DEG, f"{mode}: max {ang.max():.4f}°"


# ------------------------------------------------------------------------------------ harness

def test_harness_reads_csv_robustly(exported, tmp_path):
    _, exe = exported["9d"]
    good = ("gyr_x,gyr_y,gyr_z,acc_x,acc_y,acc_z,mag_x,mag_y,mag_z\r\n"
            + "0.01,0.02,-0.01,0.1,0.2,9.8,20,5,-40\r\n" * 3
            + " 0.01 , ,nan,0.1,0.2,9.8,20,5,-40\n"  # spaces, an empty field and nan: a bad sample
            + "0.01,0.02,-0.01,NaN,inf,9.8,20,5,-40\n"
            + "0.01,0.02,-0.01,0.1,0.2,9.8,20,5,-40\n\n")
    fin, fout = tmp_path / "in.csv", tmp_path / "out.csv"
    fin.write_text(good)
    res = subprocess.run([str(exe), str(fin), str(fout)], capture_output=True, text=True)
    assert res.returncode == 0 and res.stderr == ""
    rows = fout.read_text().splitlines()
    assert rows[0] == "w,x,y,z" and len(rows) == 7
    q = np.array([[float(v) for v in r.split(",")] for r in rows[1:]])
    assert np.all(np.isfinite(q)) and np.allclose(np.linalg.norm(q, axis=1), 1.0, atol=1e-6)

    def run_bad(text):
        fin.write_text(text)
        return subprocess.run([str(exe), str(fin), str(fout)], capture_output=True, text=True)

    r = run_bad("gyr_x,gyr_y,gyr_z,acc_x,acc_y,acc_z,mag_x,mag_y,mag_z\n0,0,0,0,0,9.8,20,abc,-40\n")
    assert r.returncode == 1 and "in.csv:2" in r.stderr and "column 8" in r.stderr
    r = run_bad("gyr_x,gyr_y,gyr_z,acc_x,acc_y,acc_z,mag_x,mag_y,mag_z\n0,0,0,0,0,9.8\n")
    assert r.returncode == 1 and "expected 9 fields, got 6" in r.stderr
    r = run_bad("a,b,c,d\n")
    assert r.returncode == 1 and "header has 4 columns, expected 9" in r.stderr
    r = run_bad("")
    assert r.returncode == 1 and "empty file" in r.stderr
    r = subprocess.run([str(exe), str(tmp_path / "missing.csv"), str(fout)], capture_output=True, text=True)
    assert r.returncode == 1 and "cannot open" in r.stderr and "missing.csv" in r.stderr
    r = subprocess.run([str(exe)], capture_output=True, text=True)
    assert r.returncode == 2 and "usage" in r.stderr


# ------------------------------------------------------------------------------ sizes, builds

def test_state_size_is_reported_and_documented(exported, model_dir):
    from togglecf.learn.compiled import CompiledModels
    from togglecf.learn.models import load_bundle

    full = CompiledModels.from_bundle(load_bundle(model_dir)).forest
    for mode, (rep, _) in exported.items():
        L, S = rep["window_max"], rep["n_classes"]  # the ring is sized for TCF_MAX_FS
        assert rep["state_bytes"] > 0 and L > rep["window"] and rep["max_fs"] == 400.0
        assert rep["state_bytes"] == cfilter.state_bytes_formula(L, S) == 4 * (69 + 12 * L + 3 * S)
        assert rep["n_trees"] < len(full.roots)  # unused outputs' trees are not exported
        names = {Path(f).name for f in rep["files"]}
        assert {"tcf_filter.h", "tcf_filter.c", "tcf_config.h", "tcf_forest.h", "tcf_forest.c", "tcf_harness.c",
                "Makefile"} <= names
        config = (Path(rep["out_dir"]) / "tcf_config.h").read_text()
        assert f"#define TCF_WINDOW_MAX {L}" in config and f"#define TCF_USE_MAG {1 if mode == '9d' else 0}" in config
        assert rep["model_hash"] in config
        assert (Path(rep["out_dir"]) / "filter_report.json").is_file()
        # gains.json holds time constants; so does the header (tcf_filter_init derives the per-sample gains
        # at its rate); the report has the Python filter's per-sample gains at the harness's default rate
        settings = _gains(rep["class_names"], rep["settings"]["static_state"], mode == "9d")
        ts = 1.0 / rep["fs"]
        want_a = [gain(t, ts) for t in settings.tau_acc]
        assert f"#define TCF_TAU_ACC_INIT {framework.c_float_array(settings.tau_acc)}" in config
        assert f"#define TCF_BIAS_TAU {c_float(settings.bias_tau)}" in config
        assert f"#define TCF_OUTPUT_TAU {c_float(settings.output_tau)}" in config
        assert "TCF_ALPHA_ACC_INIT" not in config and "TCF_DT" not in config
        np.testing.assert_allclose(rep["per_sample_gains"]["alpha_acc"], want_a, rtol=1e-12)
        if mode == "9d":  # at BROAD's rate: the former per-sample gains the time constants were converted from
            np.testing.assert_allclose(want_a[:2], [0.002, 0.0005], rtol=1e-3)


def test_sources_compile_without_warnings(exported, tmp_path):
    rep, _ = exported["9d"]
    d = Path(rep["out_dir"])
    for f in ("tcf_filter.c", "tcf_forest.c", "tcf_harness.c"):
        res = subprocess.run(["gcc", *WARN_FLAGS, "-O2", "-c", str(d / f), "-o", str(tmp_path / "x.o"), f"-I{d}"],
                             capture_output=True, text=True)
        assert res.returncode == 0 and res.stderr == "", f"{f}:\n{res.stderr}"
    if shutil.which("make"):  # the generated Makefile builds the harness
        res = subprocess.run(["make", "-s", "-C", str(d), "tcf_harness"], capture_output=True, text=True)
        assert res.returncode == 0 and res.stderr == "", res.stderr


def test_riscv_compile_and_link(exported, tmp_path):
    from togglecf.embedded.toolchain import RISCV_GCC

    if shutil.which(RISCV_GCC) is None:
        pytest.skip(f"{RISCV_GCC} not installed: no rv32imc build")
    rep, _ = exported["9d"]
    d = Path(rep["out_dir"])
    for f in ("tcf_filter.c", "tcf_forest.c"):
        res = subprocess.run([RISCV_GCC, "-march=rv32imc", "-mabi=ilp32", "--specs=picolibc.specs", *WARN_FLAGS, "-Os",
                              "-c", str(d / f), "-o", str(tmp_path / "x.o"), f"-I{d}"], capture_output=True, text=True)
        assert res.returncode == 0 and res.stderr == "", f"{f}:\n{res.stderr}"
    link = rep["linked_riscv"]
    if link is None:
        pytest.skip("picolibc not available: compiled, but no linked size")
    assert link["flash"] > rep["object_sizes"]["tcf_forest.c"]["riscv"]["text"]
    assert link["bss"] >= rep["state_bytes"]  # the filter state is a static in the probe program


# ------------------------------------------------------------------------------------ rate at init

@pytest.mark.parametrize("mode", ["9d", "6d"])
def test_c_at_another_rate_matches_python(exported, model_dir, other_rate, mode):
    """One rate-free export (harness default: the models' 285.714 Hz) run at 100 and 200 Hz
    (``tcf_filter_init(&f, fs)``) against the Python filter built at that rate. Bounds: those of the
    models' own rate above, unchanged (module docstring: ``ARITH_TOL_DEG`` for the arithmetic with
    C's own predictions, ``ANGLE_TOL_DEG`` and 97 % of the samples holding the same prediction in
    the loop): the rate enters both only through the gains and the window/hop, from the same seconds."""
    from togglecf.filters.toggling import TogglingFilter
    from togglecf.toggling import load_toggling_filter

    key, fs, gyr, acc, mag = other_rate
    rep, exe = exported[mode]
    assert rep["fs"] != fs and fs <= rep["max_fs"]
    use_mag = mode == "9d"
    mag = mag if use_mag else None
    f = load_toggling_filter(model_dir, fs, use_mag=use_mag)
    py = f.update_batch(gyr, acc, mag)
    qc, dc = cfilter.run_harness(exe, gyr, acc, mag, diagnostics=True, fs=fs)
    names = f.layout.names(rep["class_names"])
    P = np.stack([py.diagnostics[k] for k in names], axis=1)
    C = np.stack([dc[k] for k in names], axis=1)
    ref_c = TogglingFilter(fs, f.settings, use_mag=use_mag).update_batch(gyr, acc, mag, predictions=C)
    own, ang = _angles_deg(qc, ref_c.quat).max(), _angles_deg(qc, py.quat)
    probs = f.layout.probabilities
    close = np.all(np.abs(C - P)[:, probs] <= 1e-4 + 1e-4 * np.abs(P[:, probs]), axis=1)
    ok = ~np.isnan(P[:, 0])
    print(f"{key} {mode}: {len(gyr)} samples at {fs:g} Hz: C vs Python max {ang.max():.5f}°, with C's predictions "
          f"{own:.5f}°, same prediction at {close[ok].mean():.2%}, fallback {py.diagnostics['fallback'].mean():.1%} "
          f"(C {dc['fallback'].mean():.1%})")
    assert own <= ARITH_TOL_DEG, f"{key} {mode}: C vs Python with C's predictions max {own:.5f}°"
    # window from seconds at this rate: the first window ends at the same sample in C and Python
    first = window_length(fs, f.models.feature_settings.window_s) - 1
    for held, fell_back in ((P, py.diagnostics["fallback"]), (C, dc["fallback"])):
        assert np.all(np.isnan(held[:first, 0])) and (not np.isnan(held[first, 0]) or fell_back[first] == 1.0)
    # after it, a window whose feature lies within float32 rounding of a training-range bound may fall back in one
    # and not the other (module docstring): such a flip counts against the 97 % that hold the same prediction
    flips = np.mean(np.isnan(P[first:, 0]) != np.isnan(C[first:, 0]))
    assert ang.max() <= ANGLE_TOL_DEG, f"{key} {mode}: max {ang.max():.5f}°"
    assert close[ok].mean() >= 0.97 and flips <= 0.03, f"{key} {mode}: {close[ok].mean():.2%} the same, {flips:.2%} flips"


def test_rate_at_init_limits(exported, mini_trial):
    """``tcf_filter_init`` refuses a rate above ``TCF_MAX_FS`` (the harness exits with its code);
    at the default rate ``tcf_filter_update`` (dt = 1/fs) equals ``tcf_filter_update_dt`` with that dt."""
    rep, exe = exported["9d"]
    t = mini_trial
    with pytest.raises(RuntimeError, match="TCF_MAX_FS"):
        cfilter.run_harness(exe, t.gyr[:10], t.acc[:10], t.mag[:10], fs=rep["max_fs"] * 1.01)
    q = cfilter.run_harness(exe, t.gyr, t.acc, t.mag)
    qd = cfilter.run_harness(exe, t.gyr, t.acc, t.mag, dt=float(np.float32(1.0 / np.float32(rep["fs"]))))
    assert np.array_equal(q, qd)


# ------------------------------------------------------------------------------------- errors

def test_export_errors_name_the_problem(base_model_dir, model_dir, mini_trial, tmp_path, monkeypatch):
    with pytest.raises(FileNotFoundError, match="gains.json"):  # base_model_dir has no gains
        cfilter.export_c_filter(base_model_dir, tmp_path / "a", mini_trial.fs)
    with pytest.raises(ValueError, match="max_fs"):  # the harness's default rate above the largest supported
        cfilter.export_c_filter(model_dir, tmp_path / "b", 500.0, max_fs=400.0)
    with pytest.raises(FileNotFoundError, match="metadata.json"):
        cfilter.export_c_filter(tmp_path, tmp_path / "c", mini_trial.fs)
    with pytest.raises(FileNotFoundError, match="tcf_config.h"):
        cfilter.build_harness(tmp_path)
    real_which = shutil.which
    monkeypatch.setattr(toolchain.shutil, "which", lambda name, *a, **k: None if name == "gcc" else real_which(name))
    with pytest.raises(RuntimeError, match="gcc not found"):
        cfilter.build_harness(tmp_path)


def test_templates_are_package_data():
    from importlib import resources

    for name in cfilter.TEMPLATES:
        assert resources.files("togglecf").joinpath("embedded", name).is_file()
    pyproject = (Path(__file__).resolve().parents[1] / "pyproject.toml").read_text()
    assert '"embedded/*.c", "embedded/*.h"' in pyproject
