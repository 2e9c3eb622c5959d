"""Targets from ground truth, checked on synthetic trials with known truth."""
import dataclasses

import numpy as np
import pytest

from togglecf.core import quaternion as quat
from togglecf.learn.labels import (STATE_NAMES, LabelSettings, angular_velocity, bridge_gaps, estimate_mag_ref,
                             linear_acceleration, make_targets, noise_targets)
from togglecf.simulate import (EARTH_MAG_ENU, axis_sweep_trajectory, imu_from_orientation,
                               random_smooth_trajectory, static_trajectory)

FS = 285.714


def test_noise_targets_equal_injected_noise():
    q = random_smooth_trajectory(FS, 20.0, max_rate=1.5, seed=3)
    clean = imu_from_orientation(q, FS, seed=7)
    noisy = imu_from_orientation(q, FS, acc_noise=0.3, mag_noise=1.0, seed=7)
    eta_a, eta_m = noise_targets(noisy.acc, noisy.mag, q, EARTH_MAG_ENU)
    # with the true field, the targets are the injected noise up to rounding
    np.testing.assert_allclose(eta_a, noisy.acc - clean.acc, atol=1e-12)
    np.testing.assert_allclose(eta_m, noisy.mag - clean.mag, atol=1e-12)
    # the full pipeline estimates m_ref by a median of N≈5700 noisy samples: error ~ 1 µT/√N·1.25
    t = make_targets(noisy, LabelSettings(ransac_threshold=3.0))
    assert np.max(np.abs(t.mag_ref - EARTH_MAG_ENU)) < 0.1
    v = t.valid
    assert v.mean() > 0.95  # only the filter edges (half a smoothing window) are undefined
    np.testing.assert_allclose(t.eta_acc[v], (noisy.acc - clean.acc)[v], atol=1e-9)
    np.testing.assert_allclose(t.eta_mag[v], (noisy.mag - clean.mag)[v], atol=0.15)


def test_angular_velocity_equals_true_rate():
    q = random_smooth_trajectory(FS, 10.0, max_rate=3.0, seed=1)
    trial = imu_from_orientation(q, FS)  # noiseless gyro = exact rate from k-1 to k
    w = angular_velocity(q, FS, smooth_s=0.0)
    assert np.all(np.isnan(w[0]))
    np.testing.assert_allclose(w[1:], trial.gyr[1:], atol=1e-9)
    # smoothing a constant rate changes nothing (away from the edges)
    q_const = axis_sweep_trajectory([1, 2, 3], 0.0, FS, 1.0)
    rate = np.array([0.3, -0.2, 0.5])
    q_const = quat.from_rotvec(np.arange(600)[:, None] * rate / FS)
    ws = angular_velocity(q_const, FS, smooth_s=0.05)
    fin = np.all(np.isfinite(ws), axis=1)
    assert fin.sum() > 550
    np.testing.assert_allclose(ws[fin], np.tile(rate, (fin.sum(), 1)), atol=1e-9)


def test_gap_bridging():
    rate = np.array([0.0, 0.0, 1.0])
    q = quat.from_rotvec(np.arange(1000)[:, None] * rate / FS)  # constant rate: SLERP is exact
    q_gappy = q.copy()
    short = slice(100, 110)   # 10 samples = 35 ms <= 0.1 s: bridged
    long_ = slice(500, 600)   # 100 samples = 0.35 s: masked
    q_gappy[short] = np.nan
    q_gappy[long_] = np.nan
    q_gappy[:3] = np.nan      # touches the start: only one neighbour, masked
    ref, valid = bridge_gaps(q_gappy, FS, 0.1)
    assert valid[short].all() and not valid[long_].any() and not valid[:3].any()
    assert valid.sum() == 1000 - 100 - 3
    assert np.max(quat.angle_between(ref[short], q[short])) < 1e-9
    np.testing.assert_array_equal(ref[valid & ~np.isin(np.arange(1000), np.r_[100:110])],
                                  q[valid & ~np.isin(np.arange(1000), np.r_[100:110])])


def test_linear_acceleration_sensor_frame():
    n = int(10 * FS)
    t = np.arange(n) / FS
    f = 0.5
    pos = np.stack([0.2 * np.sin(2 * np.pi * f * t), np.zeros(n), 0.1 * t ** 2], axis=1)
    a_true_earth = np.stack([-0.2 * (2 * np.pi * f) ** 2 * np.sin(2 * np.pi * f * t), np.zeros(n),
                             np.full(n, 0.2)], axis=1)
    q = static_trajectory([30.0, -20.0, 60.0], n)
    a = linear_acceleration(pos, q, FS, savgol_s=0.1)
    expected = quat.rotate(quat.conjugate(q), a_true_earth)
    # cubic Savitzky-Golay is exact for the quadratic (z); for the 0.5 Hz sine the 0.1 s window
    # attenuates the 1.97 m/s² amplitude by ≈ (ω·T/2)²/14 ≈ 0.2 % (measured max error 3.0e-3)
    np.testing.assert_allclose(quat.rotate(q, a)[:, 2], 0.2, atol=1e-9)
    np.testing.assert_allclose(a, expected, atol=5e-3)


def test_motion_states_on_synthetic():
    n = int(4 * FS)
    rest = make_targets(imu_from_orientation(static_trajectory([10, 5, 0], n), FS, acc_noise=0.05,
                                             mag_noise=0.5))
    assert np.all(rest.state[rest.valid] == STATE_NAMES.index("rest"))
    sweep = axis_sweep_trajectory([0, 0, 1], 360.0, FS, 4.0)  # peak rate ≈ 2.5 rad/s
    rot = make_targets(imu_from_orientation(sweep, FS))
    w = np.linalg.norm(rot.omega, axis=1)
    fast = rot.valid & (w > 0.5)
    assert fast.sum() > 500 and np.all(rot.state[fast] == STATE_NAMES.index("rotation"))
    # binary label set: static = rest, dynamic = everything else
    traj = np.concatenate([static_trajectory([0, 0, 0], n), sweep])
    trial = imu_from_orientation(traj, FS)
    b = make_targets(trial, LabelSettings(label_set="static_dynamic"))
    s4 = make_targets(trial)
    v = b.valid
    assert set(np.unique(b.state[v])) == {0, 1}
    np.testing.assert_array_equal(b.state[v], (s4.state[v] != 0).astype(int))


def test_ransac_drops_injected_glitches():
    q = random_smooth_trajectory(FS, 30.0, max_rate=1.0, seed=5)
    trial = imu_from_orientation(q, FS, acc_noise=0.1, mag_noise=0.5, seed=2)
    rng = np.random.default_rng(0)
    q_bad = q.copy()
    glitch = np.zeros(len(q), bool)
    for s in rng.choice(np.arange(200, len(q) - 200, 150), 25, replace=False):  # 25 glitches of 40 samples
        glitch[s:s + 40] = True
    tilt = quat.from_rotvec(np.array([np.radians(40.0), 0.0, 0.0]))  # optical glitch: 40° error
    q_bad[glitch] = quat.multiply(q[glitch], tilt)
    bad_trial = dataclasses.replace(trial, opt_quat=q_bad)
    t = make_targets(bad_trial, LabelSettings(seed=1))
    v = t.valid
    # a 40° tilt moves R^T g by ≈ 6.7 m/s², far beyond the 2 m/s² threshold
    assert not t.inlier[glitch & v].any()
    assert t.inlier[~glitch & v].mean() > 0.99
    assert abs(t.inlier_fraction - (1 - glitch[v].mean())) < 0.01
    # deterministic
    t2 = make_targets(bad_trial, LabelSettings(seed=1))
    np.testing.assert_array_equal(t.inlier, t2.inlier)


def test_mag_ref_median_is_robust():
    n = 4000
    q = static_trajectory([0, 0, 30], n)
    trial = imu_from_orientation(q, FS, mag_noise=0.2)
    mag = trial.mag.copy()
    mag[:1000] += [40.0, -30.0, 10.0]  # a quarter of the samples magnetically disturbed
    est = estimate_mag_ref(mag, q, np.ones(n, bool))
    assert np.max(np.abs(est - EARTH_MAG_ENU)) < 0.2


def test_settings_validation():
    with pytest.raises(ValueError, match="label_set"):
        LabelSettings(label_set="nope")
    with pytest.raises(ValueError, match="unknown label setting"):
        LabelSettings.from_dict({"bogus": 1})
