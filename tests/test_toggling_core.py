"""The toggling CF's core driven by given predictions: exactness on simulated data, the
toggle itself, bias learning at rest, noise removal, batch/sample identity, bad inputs."""
import numpy as np
import pytest

from togglecf.core import quaternion as quat
from togglecf.filters.prediction import (
    LEARNED,
    LOW_CONFIDENCE,
    NO_PREDICTION,
    PredictionLayout,
    blend_trust,
    class_evidence,
    switch_status,
)
from togglecf.filters.toggling import TogglingFilter
from togglecf.simulate import axis_sweep_trajectory, imu_from_orientation, static_trajectory

FS = 285.7142857142857


def one_hot(n, state, n_states=2, eta_a=(0, 0, 0), eta_m=(0, 0, 0)):
    layout = PredictionLayout.of(n_states)
    p = np.zeros((n, layout.size))
    p[:, state] = 1.0
    p[:, layout.eta_acc] = eta_a
    p[:, layout.eta_mag] = eta_m
    return p


def err_deg(q, ref):
    return np.degrees(quat.angle_between(q, ref))


def test_noiseless_motion_is_tracked_exactly():
    q_true = axis_sweep_trajectory([1, 2, 0.5], 120, FS, 10.0)
    tr = imu_from_orientation(q_true, FS)
    out = TogglingFilter(FS, bias_tau=-1.0).update_batch(tr.gyr, tr.acc, tr.mag, predictions=one_hot(len(q_true), 1))
    # exact gyro + exact vectors: propagated vectors equal measured ones, corrections are null
    assert err_deg(out.quat, q_true).max() < 1e-6


def test_gain_follows_predicted_state():
    n = 2000
    tr = imu_from_orientation(static_trajectory([5, 5, 5], n), FS)
    pred = one_hot(n, 0)
    pred[1000:] = one_hot(1000, 1)
    pred[500:600, :2] = 0.5  # probabilities in between give the expected gain
    f = TogglingFilter(FS, tau_acc=(0.1732, 3.498), tau_mag=(0.3482, 6.998))  # per sample ~(0.02, 0.001), (0.01, 0.0005)
    ka, km = f.params.alpha_acc, f.params.alpha_mag
    np.testing.assert_allclose([*ka, *km], [0.02, 0.001, 0.01, 0.0005], rtol=1e-3)
    d = f.update_batch(tr.gyr, tr.acc, tr.mag, predictions=pred).diagnostics
    assert np.all(d["alpha_acc"][1:500] == ka[0]) and np.all(d["alpha_acc"][1000:] == ka[1])
    np.testing.assert_allclose(d["alpha_acc"][500:600], 0.5 * (ka[0] + ka[1]), rtol=1e-12)
    np.testing.assert_allclose(d["alpha_mag"][500:600], 0.5 * (km[0] + km[1]), rtol=1e-12)


def test_bias_learned_at_rest_and_used_in_motion():
    bias = np.array([0.004, -0.006, 0.008])  # 0.2-0.5 °/s, like BROAD's IMU
    n_rest = int(20 * FS)
    rest = static_trajectory([10, -5, 30], n_rest)
    move = axis_sweep_trajectory([0, 0, 1], 90, FS, 10.0, start=rest[-1])
    q_true = np.vstack([rest, move])
    tr = imu_from_orientation(q_true, FS, gyro_bias=bias, gyro_noise=0.002, seed=1)
    pred = one_hot(len(q_true), 1)
    pred[:n_rest] = one_hot(n_rest, 0)
    f = TogglingFilter(FS, tau_acc=(0.3482, -1.0), tau_mag=(0.3482, -1.0), bias_tau=1.748)
    out = f.update_batch(tr.gyr, tr.acc, tr.mag, predictions=pred)
    b = f.state_dict()
    # 20 s at a time constant of 1.75 s: the low-pass has converged to the bias within its noise
    np.testing.assert_allclose([b["bias_x"], b["bias_y"], b["bias_z"]], bias, atol=3e-4)
    # in motion with zero gains only gyro integration is left: the residual bias drifts < 0.1°/10 s
    assert err_deg(out.quat[-1], q_true[-1]) < 0.3
    f0 = TogglingFilter(FS, tau_acc=(0.3482, -1.0), tau_mag=(0.3482, -1.0), bias_tau=-1.0)
    out0 = f0.update_batch(tr.gyr, tr.acc, tr.mag, predictions=pred)
    assert err_deg(out0.quat[-1], q_true[-1]) > 3.0  # without the bias: ~0.6°/s over 10 s


def test_predicted_noise_is_removed():
    n = int(20 * FS)
    q_true = static_trajectory([0, 30, 0], n)
    lin = np.tile([2.0, 0.0, 0.0], (n, 1))  # constant 2 m/s² east: a tilt error of ~11.5° if kept
    tr = imu_from_orientation(q_true, FS, lin_acc_earth=lin)
    eta_a = quat.rotate(quat.conjugate(q_true[0]), [2.0, 0.0, 0.0])  # the regressor's perfect answer
    f = TogglingFilter(FS, tau_acc=(0.3482, 0.3482))
    f.set_quat(q_true[0])
    with_noise = f.update_batch(tr.gyr, tr.acc, tr.mag, predictions=one_hot(n, 0)).quat
    f = TogglingFilter(FS, tau_acc=(0.3482, 0.3482))
    denoised = f.update_batch(tr.gyr, tr.acc, tr.mag, predictions=one_hot(n, 0, eta_a=eta_a)).quat
    assert err_deg(with_noise[-1], q_true[-1]) > 10.0
    assert err_deg(denoised[-1], q_true[-1]) < 1e-6


@pytest.mark.broad
def test_update_equals_batch_and_state_splits_exactly(broad_trial):
    n = 3000
    g, a, m = broad_trial.gyr[:n], broad_trial.acc[:n], broad_trial.mag[:n]
    rng = np.random.default_rng(0)
    p = rng.random((n, 3))
    pred = np.hstack([p / p.sum(1, keepdims=True), 0.05 * rng.standard_normal((n, 6))])
    kw = dict(states=("rest", "rot", "trans"), tau_acc=(0.3482, 1.748, 6.998), tau_mag=(1.165, 3.498, -1.0),
              static_state="rest", output_tau=0.005049)
    for use_mag in (True, False):
        mm = m if use_mag else None
        full = TogglingFilter(broad_trial.fs, use_mag=use_mag, **kw).update_batch(g, a, mm, predictions=pred)
        f = TogglingFilter(broad_trial.fs, use_mag=use_mag, **kw)
        single = np.array([f.update(g[i], a[i], None if mm is None else mm[i], prediction=pred[i]) for i in range(n)])
        assert np.array_equal(single, full.quat)
        f1 = TogglingFilter(broad_trial.fs, use_mag=use_mag, **kw)
        first = f1.update_batch(g[:777], a[:777], None if mm is None else mm[:777], predictions=pred[:777])
        f2 = TogglingFilter(broad_trial.fs, use_mag=use_mag, **kw)
        f2.set_state(f1.get_state())
        second = f2.update_batch(g[777:], a[777:], None if mm is None else mm[777:], predictions=pred[777:])
        assert np.array_equal(np.vstack([first.quat, second.quat]), full.quat)


def test_bad_inputs_and_predictions_do_not_poison():
    n = 3000
    q_true = axis_sweep_trajectory([1, 0, 1], 60, FS, n / FS)
    tr = imu_from_orientation(q_true, FS)
    g, a, m = tr.gyr.copy(), tr.acc.copy(), tr.mag.copy()
    pred = one_hot(n, 1)
    g[100:110] = np.nan
    a[110:120] = 0.0
    m[120:130] = np.inf
    pred[130:140] = np.nan  # the model had no answer
    pred[140:150, 2:] = np.inf
    f = TogglingFilter(FS)
    out = f.update_batch(g, a, m, predictions=pred)
    assert np.all(np.isfinite(out.quat))
    np.testing.assert_allclose(np.linalg.norm(out.quat, axis=1), 1.0, atol=1e-12)
    # no prediction: the cautious gain (the slowest state's), and no bias update
    assert f.params.alpha_fallback_acc == min(f.params.alpha_acc)
    assert np.all(out.diagnostics["alpha_acc"][130:140] == f.params.alpha_fallback_acc)
    assert min(f.params.alpha_acc) == pytest.approx(0.0005, rel=1e-3)
    assert np.all(out.diagnostics["p_static"][130:140] == 0.0)


def _fallback_case(n=4000, seed=3):
    """A slow sweep with a gyro bias and a constant acc/mag offset that the predicted noise claims
    to be (so the learned terms visibly change the output), two states with gains far from the core's."""
    rng = np.random.default_rng(seed)
    q_true = axis_sweep_trajectory([1, 0.3, 0.5], 20, FS, n / FS)
    tr = imu_from_orientation(q_true, FS)
    g = tr.gyr + [0.01, -0.02, 0.005] + 0.002 * rng.standard_normal((n, 3))
    pred = one_hot(n, 0, eta_a=(0.3, 0, 0), eta_m=(0, 2.0, 0))
    pred[n // 2:, :2] = (0.3, 0.7)
    gains = dict(tau_acc=(0.3482, 6.998), tau_mag=(1.748, 35.0), bias_tau=1.748, bias_gate=0.05)
    return g, tr.acc, tr.mag, pred, gains


def test_fallback_below_the_confidence_floor_is_the_core():
    """c₀ = 0.75: the first half (top probability 1) runs the learned gains, the second (0.7 < 0.75)
    falls back. A filter whose every prediction is below the floor gives exactly the output of the
    same filter with both states at the slowest time constants and the learned terms off (no bias,
    no noise removal)."""
    g, a, m, pred, gains = _fallback_case()
    n = len(g)
    f = TogglingFilter(FS, confidence_floor=0.75, **gains)
    d = f.update_batch(g, a, m, predictions=pred).diagnostics
    assert np.all(d["alpha_acc"][1:n // 2] == f.params.alpha_acc[0])  # sample 0 initialises
    assert np.all(d["alpha_acc"][n // 2:] == f.params.alpha_acc[1])  # the slower state's gain: the cautious one
    assert np.all(d["p_static"][n // 2:] == 0.0)
    # the low-confidence diagnostic marks exactly the samples below the floor (NaN rows: no prediction, not low)
    assert np.array_equal(d["low_confidence"][1:], (np.arange(1, n) >= n // 2).astype(float))
    nan_pred = pred.copy()
    nan_pred[:100] = np.nan
    d_nan = TogglingFilter(FS, confidence_floor=0.75, **gains).update_batch(g, a, m, predictions=nan_pred).diagnostics
    assert d_nan["low_confidence"][:100].max() == 0.0 and d_nan["alpha_acc"][1:100].max() == f.params.alpha_acc[1]
    low = pred.copy()
    low[:, :2] = (0.6, 0.4)
    unsure = TogglingFilter(FS, confidence_floor=0.75, **gains).update_batch(g, a, m, predictions=low)
    off = TogglingFilter(FS, tau_acc=(6.998, 6.998), tau_mag=(35.0, 35.0), bias_tau=-1.0, noise_weight_acc=0.0,
                         noise_weight_mag=0.0).update_batch(g, a, m, predictions=low)
    assert np.array_equal(unsure.quat, off.quat)
    # a floor of 0 trusts every valid prediction: the learned gains apply, the output differs from the core's
    trusted = TogglingFilter(FS, confidence_floor=0.0, **gains).update_batch(g, a, m, predictions=low)
    assert err_deg(trusted.quat, off.quat).max() > 0.1


def test_confidence_floor_is_a_ratio_of_the_probabilities():
    """The confidence is the top probability over their sum, so unnormalised rows (a model whose
    outputs do not sum to 1) fall back exactly where their normalised versions do."""
    g, a, m, pred, gains = _fallback_case(n=1500)
    scaled = pred.copy()
    scaled[:, :2] *= 3.0
    f1 = TogglingFilter(FS, confidence_floor=0.75, **gains).update_batch(g, a, m, predictions=pred)
    f2 = TogglingFilter(FS, confidence_floor=0.75, **gains).update_batch(g, a, m, predictions=scaled)
    assert np.array_equal(f1.diagnostics["alpha_acc"], f2.diagnostics["alpha_acc"])


def test_settings_validation():
    with pytest.raises(ValueError, match="one time constant per state"):
        TogglingFilter(FS, tau_acc=(0.1,))
    with pytest.raises(ValueError, match="output_tau must be >= 0"):
        TogglingFilter(FS, output_tau=-1.0)
    with pytest.raises(ValueError, match="confidence_floor must be in"):
        TogglingFilter(FS, confidence_floor=1.0)
    with pytest.raises(ValueError, match="static_state"):
        TogglingFilter(FS, static_state="rest")
    with pytest.raises(ValueError, match=r"predictions: expected shape \(10, 8\)"):
        TogglingFilter(FS).update_batch(np.zeros((10, 3)), np.ones((10, 3)), np.ones((10, 3)), predictions=np.zeros((10, 7)))


def test_noise_weights_scale_the_removed_noise():
    n = int(10 * FS)
    q_true = static_trajectory([0, 30, 0], n)
    tr = imu_from_orientation(q_true, FS, lin_acc_earth=np.tile([2.0, 0.0, 0.0], (n, 1)))
    eta_a = quat.rotate(quat.conjugate(q_true[0]), [2.0, 0.0, 0.0])
    pred = one_hot(n, 0, eta_a=eta_a)
    out = {}
    for w in (0.0, 0.5, 1.0):
        f = TogglingFilter(FS, tau_acc=(0.06824, 0.06824), noise_weight_acc=w, use_mag=False)  # 6D: tilt only
        f.set_quat(q_true[0])
        out[w] = err_deg(f.update_batch(tr.gyr, tr.acc, None, predictions=pred).quat[-1], q_true[-1])
    # 2 m/s² left over tilts by atan(2/9.81) = 11.5°, half of it by atan(1/9.81) = 5.8°, none by 0
    # (heading moves only at second order in 6D: 0.2° tolerance)
    assert out[0.0] == pytest.approx(11.5, abs=0.2) and out[0.5] == pytest.approx(5.8, abs=0.2) and out[1.0] < 1e-6


def test_prediction_layout_and_the_two_fallback_rules():
    """The row layout names its parts; the toggling CF's hard switch and the learned VQF's trust ramp
    (filters.prediction) agree on what is valid and differ where the docstring says."""
    layout = PredictionLayout.of(4)
    assert (layout.n_states, layout.eta_acc_index, layout.eta_mag_index, layout.size) == (4, 4, 7, 10)
    row = np.arange(10.0)
    assert row[layout.probabilities].tolist() == [0, 1, 2, 3] and row[layout.eta_acc].tolist() == [4, 5, 6]
    assert row[layout.eta_mag].tolist() == [7, 8, 9] and layout.outputs(layout.eta) == [4, 5, 6, 7, 8, 9]
    assert layout.names(("a", "b", "c", "d"))[3:6] == ["p_d", "eta_acc_x", "eta_acc_y"]
    for p, floor, status, trust in (([0.7, 0.1, 0.1, 0.1], 0.5, LEARNED, 0.4), ([0.4, 0.2, 0.2, 0.2], 0.5, LOW_CONFIDENCE, 0.0),
                                    ([np.nan, 0.2, 0.2, 0.2], 0.0, NO_PREDICTION, 0.0), ([0.0] * 4, 0.0, NO_PREDICTION, 0.0)):
        valid, top, total = class_evidence.py_func(layout, np.array(p + [0.0] * 6))
        assert switch_status.py_func(valid, top, total, floor) == status
        assert blend_trust.py_func(valid, top, total, floor) == pytest.approx(trust)
