"""The VQF core with learned time constants (filters.vqf_toggling): learning off is the core,
the fallback and the bounds hold, update == update_batch, the in-loop models equal the
prediction-driven filter, `togglecf train` learns and stores its gains, and the field-change
back-off (step 3b) is its definition, backs off a disturbance and not the turning, and is off at 0."""
import json
import shutil
from dataclasses import replace

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from togglecf import simulate
from togglecf.core.quaternion import angle_between
from togglecf.filters import VQFCoreFilter
from togglecf.filters.prediction import PredictionLayout
from togglecf.filters.vqf_toggling import TAU_ACC_RANGE, VQFTogglingFilter, VQFTogglingSettings
from togglecf.registry import VQF_TOGGLING, FilterSpec
from togglecf.run.config import PRETRAINED_DEFAULTS, RELEARN_DEFAULTS, load_config, pretrained_config, relearn_search
from togglecf.run.train import run_training
from togglecf.toggling import load_gains
from togglecf.toggling.gains import VQFGainSearch
from togglecf.toggling.inloop import ModelVQFTogglingFilter

STATES = ("rest", "rotation", "linear_acceleration", "vibration")


def _predictions(n, rng, n_states=4):
    p = rng.random((n, n_states))
    p /= p.sum(axis=1, keepdims=True)
    p = np.repeat(p[:: 30], 30, axis=0)[:n]  # held between "hops", as the models give them
    layout = PredictionLayout.of(n_states)
    rows = np.empty((n, layout.size))
    rows[:, layout.probabilities] = p
    rows[:, layout.eta] = 0.1 * rng.standard_normal((n, 6))
    return rows


def test_learning_off_is_the_core(mini_trial, rng):
    t = mini_trial
    core = VQFCoreFilter(t.fs).update_batch(t.gyr, t.acc, t.mag)
    off = VQFTogglingSettings(states=STATES)  # every per-state value = the core's; noise weights 0
    no_pred = VQFTogglingFilter(t.fs, off).update_batch(t.gyr, t.acc, t.mag)
    assert np.array_equal(no_pred.quat, core.quat)  # NaN predictions: the core's coefficients, untouched
    with_pred = VQFTogglingFilter(t.fs, off).update_batch(t.gyr, t.acc, t.mag, predictions=_predictions(t.n_samples, rng))
    # the coefficients are recomputed from exp(ln τ): equal to rounding (1e-12 rad is 6e-11°)
    assert np.max(angle_between(with_pred.quat, core.quat)) < 1e-9


def test_fallback_on_nan_and_low_confidence(mini_trial):
    t = mini_trial
    s = VQFTogglingSettings(states=("a", "b"), tau_acc_states=(1.0, 20.0), tau_mag_states=(3.0, 50.0),
                            confidence_floor=0.6)
    n = t.n_samples
    uncertain = np.hstack([np.full((n, 2), 0.5), np.zeros((n, 6))])  # top probability 0.5 < c₀: the core's τ
    o = VQFTogglingFilter(t.fs, s).update_batch(t.gyr, t.acc, t.mag, predictions=uncertain)
    assert np.allclose(o.diagnostics["tau_acc"], s.tau_acc) and np.allclose(o.diagnostics["tau_mag"], s.tau_mag)
    assert np.all(o.diagnostics["trust"] == 0.0)
    sure = np.hstack([np.tile([1.0, 0.0], (n, 1)), np.zeros((n, 6))])
    o = VQFTogglingFilter(t.fs, s).update_batch(t.gyr, t.acc, t.mag, predictions=sure)
    assert np.allclose(o.diagnostics["tau_acc"], 1.0) and np.all(o.diagnostics["trust"] == 1.0)
    half = np.hstack([np.tile([0.8, 0.2], (n, 1)), np.zeros((n, 6))])  # λ = (0.8 − 0.6)/0.4 = 0.5
    o = VQFTogglingFilter(t.fs, s).update_batch(t.gyr, t.acc, t.mag, predictions=half)
    blend = np.exp(0.5 * (0.8 * np.log(1.0) + 0.2 * np.log(20.0)) + 0.5 * np.log(s.tau_acc))
    assert np.allclose(o.diagnostics["tau_acc"], blend)
    nan = np.full((n, 8), np.nan)
    o = VQFTogglingFilter(t.fs, s).update_batch(t.gyr, t.acc, t.mag, predictions=nan)
    assert np.array_equal(o.quat, VQFCoreFilter(t.fs, s.core_settings).update_batch(t.gyr, t.acc, t.mag).quat)


def test_predicted_disturbance_scales_the_heading_gain_within_the_cores_rejection_factor(mini_trial):
    """Step 3 on the predicted disturbance (``mag_backoff_measured=False``, the default):
    k_mag / (1 + min((|η̂_m| / σ_m)², f_reject − 1)) in 9D, f_reject the core's
    ``mag_rejection_factor``; σ_m = 0 or 6D: the core's k_mag. The core's own norm/dip rejection
    is switched off here so that k is the modulated gain on every sample."""
    t = mini_trial
    n = t.n_samples
    layout = PredictionLayout.of(2)
    pred = np.zeros((n, layout.size))
    pred[:, 0] = 1.0
    pred[:, layout.eta_mag] = (6.0, 0.0, 8.0)  # |η̂_m| = 10 µT
    plain = dict(states=("a", "b"), mag_dist_rejection_enabled=False)
    # (10/5)² = 4: k / 5 where the core's rejection factor allows it (10), k / 2 at VQF's factor 2
    wide = VQFTogglingSettings(**plain, mag_disturbance_scale=5.0, mag_rejection_factor=10.0)
    s = VQFTogglingSettings(**plain, mag_disturbance_scale=5.0)
    assert s.mag_backoff_measured is False and s.mag_rejection_factor == 2.0
    off = VQFTogglingFilter(t.fs, VQFTogglingSettings(**plain)).update_batch(t.gyr, t.acc, t.mag, predictions=pred)
    k_off = off.diagnostics["k_mag"]
    # after the start-up phase (M5: k >= 1/N until N·Ts > τ_mag = 9 s, sample 2572 at 285.7 Hz)
    steady = (np.arange(n) * (1.0 / t.fs) > 1.2 * s.tau_mag) & (k_off > 0)
    assert steady.sum() > 500
    for settings, divisor in ((wide, 5.0), (s, 2.0)):
        k_on = VQFTogglingFilter(t.fs, settings).update_batch(t.gyr, t.acc, t.mag, predictions=pred).diagnostics["k_mag"]
        np.testing.assert_allclose(k_on[steady], k_off[steady] / divisor, rtol=1e-12)
    six = VQFTogglingFilter(t.fs, s, use_mag=False).update_batch(t.gyr, t.acc, None, predictions=pred)
    six_off = VQFTogglingFilter(t.fs, VQFTogglingSettings(states=("a", "b")), use_mag=False).update_batch(
        t.gyr, t.acc, None, predictions=pred)
    assert np.array_equal(six.quat, six_off.quat)  # no magnetometer: nothing to scale


def test_backoff_acts_on_no_more_disturbance_than_the_magnetometer_shows(mini_index, mini_names):
    """Step 3 with ``mag_backoff_measured``: e = min((|η̂_m| / σ_m)², d² / σ_m²), d² =
    n² + n_ref² − 2 n n_ref cos(dip − dip_ref) from the state before each sample. A slow reference
    (scipy's rotation for the dip, the core's reference read from the state by name) gives k_mag on
    every sample where the core itself does not reject the field. The field is scaled by 1.05 after
    8 s (a disturbance the core's 10 % norm threshold lets through): the back-off grows there, and
    a constant |η̂_m| = 10 µT never backs off more than the deviation the sensor shows."""
    t = mini_index.load(mini_names[0])  # 02: undisturbed (BROAD), or synthetic
    n = t.n_samples
    mag = t.mag.copy()
    late = np.arange(n) / t.fs > 8.0
    mag[late] *= 1.05
    pred = np.hstack([np.tile([1.0, 0.0], (n, 1)), np.zeros((n, 3)), np.tile([6.0, 0.0, 8.0], (n, 1))])
    sigma = 5.0
    # the core's first field reference after 1 s of any motion (VQF: 5 s of rotation), τ_mag 3 s:
    # k_mag >= 1/N ends after 3.6 s (M5)
    s = VQFTogglingSettings(states=("a", "b"), tau_mag=3.0, mag_new_first_time=1.0, mag_new_min_gyr=0.0,
                            mag_disturbance_scale=sigma, modulation_tau=3.0, mag_backoff_measured=True)
    f = VQFTogglingFilter(t.fs, s)
    k, expected, core_k = np.zeros(n), np.zeros(n), np.zeros(n)
    for i in range(n):
        before = f.state_dict()
        f.update(t.gyr[i], t.acc[i], mag[i], prediction=pred[i])
        d = f.last_diagnostics
        k[i] = d["k_mag"]
        core_k[i] = (1.0 - np.exp(-1.0 / (t.fs * d["tau_mag"]))) if d["mag_dist"] == 0 else np.nan
        n_ref, dip_ref = before["mag_ref_norm"], before["mag_ref_dip"]
        if n_ref > 0:
            w, x, y, z = before["quat"]
            m_e = Rotation.from_quat([x, y, z, w]).apply(mag[i])
            nm = np.linalg.norm(mag[i])
            dev2 = nm ** 2 + n_ref ** 2 - 2 * nm * n_ref * np.cos(-np.arcsin(m_e[2] / nm) - dip_ref)
            expected[i] = core_k[i] / (1.0 + min(4.0, dev2 / sigma ** 2))
        else:
            expected[i] = core_k[i]
    steady = (np.arange(n) / t.fs > 4.0) & np.isfinite(core_k)  # after M5, where the core does not reject
    assert steady[~late].sum() > 200 and steady[late].sum() > 500
    # float64 in both; the slow reference takes another path to the dip: 1e-9 relative
    np.testing.assert_allclose(k[steady], expected[steady], rtol=1e-9)
    backoff = core_k / k
    assert np.all(backoff[steady] <= 5.0 + 1e-12)  # never more than the predicted (10/5)² = 4
    # the shown disturbance: 5 % of the field (~2 µT at BROAD's ~45 µT) against noise before it
    assert np.median(backoff[steady & late]) > 1.1 * np.median(backoff[steady & ~late])


def test_rest_thresholds_per_state_change_rest_detection(mini_trial):
    """A state whose rest thresholds are 5x the core's detects rest on more samples, where the
    motion makes the deviations from the low-pass exceed the core's thresholds."""
    t = mini_trial
    n = t.n_samples
    pred = np.hstack([np.tile([1.0, 0.0], (n, 1)), np.zeros((n, 6))])
    core = VQFTogglingFilter(t.fs, VQFTogglingSettings(states=("a", "b"))).update_batch(t.gyr, t.acc, t.mag,
                                                                                         predictions=pred)
    loose = VQFTogglingSettings(states=("a", "b"), rest_th_gyr_states=(10.0, 2.0), rest_th_acc_states=(2.5, 0.5))
    o = VQFTogglingFilter(t.fs, loose).update_batch(t.gyr, t.acc, t.mag, predictions=pred)
    assert o.diagnostics["rest"].sum() > core.diagnostics["rest"].sum()
    assert np.all(o.diagnostics["rest"] >= core.diagnostics["rest"])  # looser thresholds never lose a rest sample


def test_bounds_keep_every_correction_on():
    with pytest.raises(ValueError, match="may not switch the correction off"):
        VQFTogglingSettings(states=("a", "b"), tau_acc_states=(1.0, TAU_ACC_RANGE[1] * 10))
    with pytest.raises(ValueError, match="may not switch the correction off"):
        VQFTogglingSettings(states=("a", "b"), rest_th_gyr_states=(2.0, 50.0))
    with pytest.raises(ValueError, match="mag_disturbance_scale"):
        VQFTogglingSettings(states=("a", "b"), mag_disturbance_scale=-1.0)
    with pytest.raises(ValueError, match="one value per state"):
        VQFTogglingSettings(states=("a", "b"), tau_mag_states=(9.0,))


def test_sigma_motion_is_not_learned_by_default():
    """σ_motion is a property of the gyroscope (docs/concepts/vqf-core.md): by default the search,
    in code and in the shipped config, offers only the core's value, so the learned filter keeps it."""
    core = VQFTogglingSettings(states=STATES).bias_sigma_motion
    for search in (VQFGainSearch(), VQFGainSearch.from_dict(load_config()["gains"]["vqf"])):
        grids = dict(search.candidates(search.start(STATES)))
        for s in STATES:
            assert [v for v, _ in grids[f"bias_sigma_motion_states[{s}]"]] == [core]
        assert len(grids[f"tau_acc_states[{STATES[0]}]"]) > 1  # τ_acc is still searched per state


def test_update_equals_batch_and_state_splits(mini_trial, rng):
    t = mini_trial
    s = VQFTogglingSettings(states=STATES, tau_acc_states=(1.0, 3.0, 8.0, 15.0), noise_weight_acc=0.5)
    P = _predictions(2000, rng)
    batch = VQFTogglingFilter(t.fs, s).update_batch(t.gyr[:2000], t.acc[:2000], t.mag[:2000], predictions=P).quat
    f = VQFTogglingFilter(t.fs, s)
    one = np.array([f.update(t.gyr[i], t.acc[i], t.mag[i], prediction=P[i]) for i in range(2000)])
    assert np.array_equal(one, batch)
    g = VQFTogglingFilter(t.fs, s)
    g.update_batch(t.gyr[:900], t.acc[:900], t.mag[:900], predictions=P[:900])
    h = VQFTogglingFilter(t.fs, s)
    h.set_state(g.get_state())
    rest = h.update_batch(t.gyr[900:2000], t.acc[900:2000], t.mag[900:2000], predictions=P[900:]).quat
    assert np.array_equal(rest, batch[900:])


@pytest.fixture(scope="module")
def vqf_model_dir(mini_index, tmp_path_factory):
    """Tiny models with VQF-core gains learned (CV on 3 mini trials, one sweep of small grids)."""
    cfg = load_config()
    cfg["run"]["cv_folds"] = 3
    cfg["classifier"].update(n_estimators=6, max_depth=3)
    cfg["regressor"].update(n_estimators=3, max_depth=3)
    cfg["gains"].update(modes=["vqf_9d"], vqf={"tau_acc": [1.0, 3.0, 8.0], "tau_mag": [9.0], "bias_sigma_motion": [0.1],
                                             "confidence_floor": [0.0], "noise_weight_acc": [0.0],
                                             "noise_weight_mag": [0.0], "sweeps": 1})
    out = tmp_path_factory.mktemp("vqfmodels") / "m"
    run_training(cfg, data_dir=mini_index.root, trials="02,07,24", out=out, cv=True, verbose=False)
    return out


def test_train_learns_vqf_gains_and_the_registry_runs_them(vqf_model_dir, mini_index, mini_names):
    s = load_gains(vqf_model_dir, kind=VQF_TOGGLING)
    assert isinstance(s, VQFTogglingSettings) and all(v in (1.0, 3.0, 8.0) for v in s.tau_acc_states)
    with pytest.raises(KeyError, match="no gains of mode .*vqf_6d"):
        load_gains(vqf_model_dir, use_mag=False, kind=VQF_TOGGLING)
    t = mini_index.load(mini_names[1])  # 07
    f = FilterSpec(VQF_TOGGLING, models=vqf_model_dir).build(t.fs)
    assert isinstance(f, ModelVQFTogglingFilter)
    o = f.update_batch(t.gyr, t.acc, t.mag)
    # the in-loop models equal the prediction-driven filter fed the predictions the loop held
    names = [f"p_{c}" for c in f.models.class_names] + [f"eta_{k}_{ax}" for k in ("acc", "mag") for ax in "xyz"]
    P = np.column_stack([o.diagnostics[n] for n in names])
    ref = VQFTogglingFilter(t.fs, s).update_batch(t.gyr, t.acc, t.mag, predictions=P)
    assert np.array_equal(o.quat, ref.quat)


def _switching_record(fs, seconds=120.0, period_s=0.5, amp=4.0):
    """A still sensor (level, gravity on z) shaken along x by a zero-mean square wave of ±``amp``
    m/s² with period ``period_s``, and predictions made from that same signal: state 0 while the
    push is +x, state 1 while it is −x (one-hot, held as the models hold them)."""
    n = int(seconds * fs)
    t = np.arange(n) / fs
    push = np.where(np.sin(2 * np.pi * t / period_s) >= 0.0, amp, -amp)
    acc = np.zeros((n, 3))
    acc[:, 0], acc[:, 2] = push, 9.81
    pred = np.zeros((n, 10))
    pred[:, 0], pred[:, 1] = push > 0, push < 0
    return np.zeros((n, 3)), acc, pred


def _final_tilt_deg(fs, modulation_tau):
    gyr, acc, pred = _switching_record(fs)
    s = VQFTogglingSettings(states=STATES, tau_acc_states=(1.0, 10.0, 3.0, 3.0), modulation_tau=modulation_tau)
    q = VQFTogglingFilter(fs, s, use_mag=False).update_batch(gyr, acc, None, predictions=pred).quat[-1]
    return np.degrees(angle_between(q[None], np.array([[1.0, 0.0, 0.0, 0.0]])))[0]


def test_gains_store_their_backoff_law(vqf_model_dir, tmp_path):
    """A gains.json stores ``mag_backoff_measured``, so models trained with the measured back-off
    (the default until 2026-12) keep it; one without the key backs off on the predicted disturbance
    (bounded by the core's rejection factor, the default now)."""
    assert load_gains(vqf_model_dir, kind=VQF_TOGGLING).mag_backoff_measured is False
    for stored in (True, None):
        old = tmp_path / f"m{stored}"
        shutil.copytree(vqf_model_dir, old)
        doc = json.loads((old / "gains.json").read_text())
        if stored is None:
            del doc["vqf_9d"]["settings"]["mag_backoff_measured"]
        else:
            doc["vqf_9d"]["settings"]["mag_backoff_measured"] = stored
        (old / "gains.json").write_text(json.dumps(doc))
        assert load_gains(old, kind=VQF_TOGGLING).mag_backoff_measured is bool(stored)


@pytest.mark.parametrize("fs", [100.0, 285.714])
def test_time_constants_that_follow_the_signal_bias_the_tilt_unless_they_follow_slowly(fs):
    """Why ``modulation_tau`` exists (issue 24). The τ_acc low-pass is a running average whose weights are its
    gains: switched with every prediction, and predictions made from the signal itself, it weighs the +x pushes
    (τ 1 s) ten times more than the −x ones (τ 10 s), so the zero-mean shaking leaves a tilt. Its size follows
    from the weights: with gains ∝ 1/τ² for the second-order low-pass the average push is about
    4 (1 − 0.01)/(1 + 0.01) ≈ 3.9 m/s², atan(3.9 / 9.81) ≈ 22° (measured 21.8° at both rates); anything above
    10° shows the bias. Followed with a 3-s time constant (six switching periods) τ sits near its geometric
    mean on both halves and the bias nearly vanishes: below a tenth of the switched one (measured 0.05° at
    100 Hz, 0.01° at 285.7 Hz)."""
    switched, followed = _final_tilt_deg(fs, 0.0), _final_tilt_deg(fs, 3.0)
    assert switched > 10.0
    assert followed < 0.1 * switched


@pytest.mark.parametrize("fs", [100.0, 400.0])
def test_modulation_follows_with_its_time_constant_in_seconds(fs):
    """First-order law in seconds at any rate: one time constant after a switch from the core's τ_acc (3 s) to a
    state's 10 s, ln τ has moved 1 − e⁻¹ of the way (to the per-sample discretisation: 1/fs of 3 s ≤ 0.3 %);
    after ten it is there."""
    n = int(40 * fs)
    pred = np.zeros((n, 10))
    pred[:, 1] = 1.0
    s = VQFTogglingSettings(states=STATES, tau_acc_states=(3.0, 10.0, 3.0, 3.0), modulation_tau=3.0)
    z = np.zeros((n, 3))
    z[:, 2] = 9.81
    tau = VQFTogglingFilter(fs, s, use_mag=False).update_batch(np.zeros((n, 3)), z, None, predictions=pred).diagnostics["tau_acc"]
    moved = np.log(tau / 3.0) / np.log(10.0 / 3.0)
    assert abs(moved[int(3.0 * fs) - 1] - (1 - np.exp(-1))) < 5e-3
    assert abs(tau[int(30.0 * fs)] - 10.0) < 1e-3


def test_learning_off_is_the_core_with_a_followed_modulation(mini_trial, rng):
    """``modulation_tau`` only changes how the learned values are reached: with every per-state value at the
    core's, the filter is the core (as ``test_learning_off_is_the_core``, to rounding)."""
    t = mini_trial
    core = VQFCoreFilter(t.fs).update_batch(t.gyr, t.acc, t.mag)
    off = VQFTogglingSettings(states=STATES, modulation_tau=3.0)
    o = VQFTogglingFilter(t.fs, off).update_batch(t.gyr, t.acc, t.mag, predictions=_predictions(t.n_samples, rng))
    assert np.max(angle_between(o.quat, core.quat)) < 1e-9
    with pytest.raises(ValueError, match="modulation_tau"):
        VQFTogglingSettings(states=STATES, modulation_tau=-1.0)


def test_field_change_state_is_the_low_pass_of_the_6d_earth_frame_field(mini_trial):
    """Step 3b's state after a trial equals its definition computed here in numpy: the field in the earth
    frame of the core's 6D orientation (the 6D core's output: the heading correction never touches q_6D, so the
    9D filter's q_6D is the 6D core's), low-passed with 1 − exp(−Ts/τ_f) from the first valid sample, e_f the
    last sample's (|m_E − LP| / σ_f)². Tolerance: float64 rounding over 4000 samples (1e-9 µT)."""
    t = mini_trial
    scale, tau = 10.0, 1.0
    s = VQFTogglingSettings(states=STATES, field_change_scale=scale, field_change_tau=tau)
    f = VQFTogglingFilter(t.fs, s)
    f.update_batch(t.gyr, t.acc, t.mag)
    q6 = VQFCoreFilter(t.fs, use_mag=False).update_batch(t.gyr, t.acc).quat
    me = Rotation.from_quat(q6[:, [1, 2, 3, 0]]).apply(t.mag)  # sensor -> earth, scipy's [x, y, z, w]
    ts, k = 1.0 / t.fs, 1.0 - np.exp(-1.0 / (t.fs * tau))
    ok = np.isfinite(t.mag).all(axis=1) & (np.linalg.norm(t.mag, axis=1) > 1e-9)
    lp, age, e = None, 0.0, 0.0
    for i in np.flatnonzero(ok):
        if lp is None:
            lp = me[i].copy()
            continue
        d = me[i] - lp
        age += ts
        if age >= tau - 0.5 * ts:
            e = float(d @ d) / scale ** 2
        lp = lp + k * d
    np.testing.assert_allclose(f.record.field_lp, lp, rtol=0, atol=1e-9)
    assert f.record.field_change_disturbance == pytest.approx(e, rel=1e-9, abs=1e-15)
    assert f.record.field_lp_t == pytest.approx(ts * (ok.sum() - 1), rel=1e-12)


def _field_change_run(fs, scale, disturbance=(20.0, 0.0, 0.0)):
    """A turning sensor (simulate.gimbal_trajectory, 40 s) in the earth's field, a constant field
    ``disturbance`` [µT, ENU] added from 20 s to 30 s; the learned VQF with step 3b at ``scale`` σ_f [µT],
    no prediction. Returns the per-sample back-off 1 + e and the trial."""
    n = int(40 * fs)
    q = simulate.gimbal_trajectory(fs, 40.0)
    t = simulate.imu_from_orientation(q, fs, mag_disturbance_earth=simulate.mag_disturbance_intervals(
        n, fs, ((20.0, 30.0, disturbance),)))
    f = VQFTogglingFilter(fs, VQFTogglingSettings(states=STATES, field_change_scale=scale))
    backoff = np.empty(n)
    for i in range(n):
        f.update(t.gyr[i], t.acc[i], t.mag[i])
        backoff[i] = f.record.mag_backoff
    return backoff, t


def test_field_change_backs_off_a_disturbance_coming_and_going_and_not_the_turning():
    """Noise-free signals: while the sensor turns in the undisturbed field the gyroscope explains the field's
    turning and the back-off stays at 1 (to the 6D estimate's own error); a 20 µT field coming and going
    backs off the heading gain by the core's rejection factor (2) at once, never more, and not before it
    came; a 10 s constant disturbance is accepted as the field after a few τ_f."""
    fs = 100.0
    backoff, t = _field_change_run(fs, scale=5.0)
    time = np.arange(len(backoff)) / fs
    undisturbed = (time > 2.0) & (time < 20.0)
    assert backoff[undisturbed].max() < 1.01  # (e_f < 0.01: |m_E − LP| < 0.5 µT of the 6D estimate's error)
    assert backoff.max() == pytest.approx(2.0) and backoff.max() <= 2.0  # capped at f_reject
    onset, end = int(20.0 * fs), int(30.0 * fs)
    assert backoff[onset + 1] == pytest.approx(2.0)  # the next sample backs off (step 3b runs after the step)
    assert backoff[onset + int(8 * fs):end].max() < 1.01  # accepted after 8 s (8 τ_f)
    assert backoff[end + 1] == pytest.approx(2.0)  # and the field's return is a change too
    assert backoff[-int(2 * fs):].max() < 1.01


def test_field_change_is_off_at_zero_and_in_6d_and_checked(mini_trial):
    """σ_f = 0 (the default) is the filter without step 3b, bit for bit; in 6D it is off whatever σ_f
    (no magnetometer); settings outside their range are refused with the field's name."""
    t = mini_trial
    base = VQFTogglingFilter(t.fs, VQFTogglingSettings(states=STATES, mag_disturbance_scale=10.0))
    off = VQFTogglingFilter(t.fs, VQFTogglingSettings(states=STATES, mag_disturbance_scale=10.0,
                                                      field_change_scale=0.0, field_change_tau=3.0))
    assert np.array_equal(base.update_batch(t.gyr, t.acc, t.mag).quat, off.update_batch(t.gyr, t.acc, t.mag).quat)
    on = VQFTogglingSettings(states=STATES, field_change_scale=5.0)
    assert not on.learning_off(use_mag=True) and on.learning_off(use_mag=False)
    q6_on = VQFTogglingFilter(t.fs, on, use_mag=False).update_batch(t.gyr, t.acc).quat
    assert np.array_equal(q6_on, VQFCoreFilter(t.fs, use_mag=False).update_batch(t.gyr, t.acc).quat)
    on9 = VQFTogglingFilter(t.fs, on).update_batch(t.gyr, t.acc, t.mag).quat
    assert np.max(angle_between(on9, base.update_batch(t.gyr, t.acc, t.mag).quat)) > 1e-6  # it does act in 9D
    for bad in (dict(field_change_scale=-1.0), dict(field_change_scale=np.inf), dict(field_change_tau=0.0),
                dict(field_change_tau=np.nan)):
        with pytest.raises(ValueError, match=next(iter(bad))):
            VQFTogglingSettings(states=STATES, **bad)


def test_search_offers_the_field_change_scale_in_9d_only_and_off_by_default():
    """σ_f is a coordinate of the descent in 9D with its grid (a config's ``[gains.vqf] field_change_scale``),
    none in 6D; by default its grid is 0 alone, so the descent never moves it (every existing model's
    search is unchanged)."""
    start = VQFGainSearch().start(STATES)
    assert dict(VQFGainSearch().candidates(start, use_mag=True))["field_change_scale"] == [
        (0.0, {"field_change_scale": 0.0})]
    grid = VQFGainSearch.from_dict({"field_change_scale": [0.0, 10.0, 20.0]})
    assert [v for v, _ in dict(grid.candidates(start, use_mag=True))["field_change_scale"]] == [0.0, 10.0, 20.0]
    assert "field_change_scale" not in dict(grid.candidates(start, use_mag=False))


def test_the_pretrained_recipe_keeps_tau_acc_and_takes_the_mean_over_datasets():
    """``[gains.pretrained]`` (``pretrained_config``, the search of the model trained on several sensors): the
    package's config and a config without the table keep τ_acc at the core's 3 s and take the mean-over-datasets
    objective, every other coordinate as ``[gains.vqf]``, which itself is not changed; the table's own values win,
    its unknown keys are refused with the table's name."""
    cfg = load_config()
    train = VQFGainSearch.from_dict(cfg["gains"]["vqf"])
    pre = VQFGainSearch.from_dict(pretrained_config(cfg)["gains"]["vqf"])
    assert PRETRAINED_DEFAULTS == {"tau_acc": (3.0,), "objective": "mean_dataset_log_ratio"}
    assert pre.tau_acc == (3.0,) and pre.objective == "mean_dataset_log_ratio"
    assert replace(pre, tau_acc=train.tau_acc, objective=train.objective) == train
    assert train.tau_acc == (1.0, 2.0, 3.0, 5.0, 10.0) and train.objective == "worst_dataset_log_ratio"
    assert VQFGainSearch.from_dict(cfg["gains"]["vqf"]) == train  # the copy left cfg as it was
    bare = load_config({"gains": {"vqf": {"mag_disturbance_scale": [0.0, 20.0]}}})
    bare_pre = VQFGainSearch.from_dict(pretrained_config(bare)["gains"]["vqf"])
    assert bare_pre.tau_acc == (3.0,) and bare_pre.mag_disturbance_scale == (0.0, 20.0)
    own = load_config({"gains": {"pretrained": {"tau_acc": [2.0, 3.0], "objective": "worst_dataset_log_ratio"}}})
    own_pre = VQFGainSearch.from_dict(pretrained_config(own)["gains"]["vqf"])
    assert own_pre.tau_acc == (2.0, 3.0) and own_pre.objective == "worst_dataset_log_ratio"
    with pytest.raises(ValueError, match=r"unknown \[gains.pretrained\] setting\(s\) \['sigma_m'\]"):
        load_config({"gains": {"pretrained": {"sigma_m": [1.0]}}})


def test_relearning_searches_the_field_change_scale_and_training_does_not():
    """``[gains.relearn]`` (``relearn_search``, the search of ``train --from-pretrained``): the package's config and a
    config without the table search σ_f on ``RELEARN_DEFAULTS``' grid, every other coordinate as ``[gains.vqf]``;
    the training search (``[gains.vqf]``) keeps it off; the table's own values win, and its unknown keys are
    refused with the table's name."""
    cfg = load_config()
    train, relearn = VQFGainSearch.from_dict(cfg["gains"]["vqf"]), relearn_search(cfg)
    assert train.field_change_scale == (0.0,)
    assert relearn.field_change_scale == RELEARN_DEFAULTS["field_change_scale"] == (0.0, 10.0, 20.0, 50.0)
    assert replace(relearn, field_change_scale=(0.0,)) == train
    bare = load_config({"gains": {"vqf": {"tau_acc": [2.0, 4.0]}}})
    assert relearn_search(bare).field_change_scale == RELEARN_DEFAULTS["field_change_scale"]
    assert relearn_search(bare).tau_acc == (2.0, 4.0)
    off = load_config({"gains": {"vqf": {"field_change_scale": [0.0, 5.0]}, "relearn": {"field_change_scale": [0.0]}}})
    assert relearn_search(off).field_change_scale == (0.0,)
    assert VQFGainSearch.from_dict(off["gains"]["vqf"]).field_change_scale == (0.0, 5.0)
    with pytest.raises(ValueError, match=r"unknown \[gains.relearn\] setting\(s\) \['sigma_f'\]"):
        load_config({"gains": {"relearn": {"sigma_f": [1.0]}}})
