"""Gain learning finds what the physics says: trust the accelerometer at rest, not during
linear-acceleration bursts, and learn the gyro bias at rest."""
import dataclasses

import numpy as np
import pytest

from togglecf.core import quaternion as quat
from togglecf.toggling.gains import EvaluationMemo, GainSearch, learn_gains, mean_total_rmse, trials_digest
from togglecf.filters.toggling import TogglingSettings
from togglecf.simulate import imu_from_orientation, random_smooth_trajectory

FS = 100.0


def make_trial(seed):
    rng = np.random.default_rng(seed)
    n_rest, n_move = int(15 * FS), int(30 * FS)
    move = random_smooth_trajectory(FS, n_move / FS, max_rate=1.0, seed=seed)
    q = np.vstack([np.tile(move[0], (n_rest, 1)), move])
    lin = np.zeros((len(q), 3))
    burst = np.zeros(len(q), bool)
    for start in rng.integers(n_rest, len(q) - 200, 6):  # 2 s bursts of 3 m/s² linear acceleration
        burst[start:start + 200] = True
    lin[burst] = 3.0 * rng.standard_normal(3)
    t = imu_from_orientation(q, FS, lin_acc_earth=lin, gyro_bias=[0.01, -0.008, 0.005], gyro_noise=0.003,
                             acc_noise=0.05, mag_noise=0.3, seed=seed)
    pred = np.zeros((len(q), 8))
    rest = np.arange(len(q)) < n_rest
    pred[rest, 0] = 1.0  # the "classifier" is perfect here: rest vs dynamic
    pred[~rest, 1] = 1.0
    return t, pred


def test_learned_gains_follow_the_motion_state():
    trials, preds = zip(*(make_trial(s) for s in (1, 2)))
    # time constants [s]: per sample 0 (off), 0.0003, 0.001, 0.003, 0.01, 0.03 at this test's 100 Hz
    search = GainSearch(tau=(-1.0, 33.33, 9.995, 3.328, 0.995, 0.3283), output_tau=(0.0,), bias_tau=(-1.0, 3.328),
                        mag_disturbance_scale=(0.0,), sweeps=2)
    settings, history = learn_gains(trials, preds, ("rest", "dynamic"), "rest", search=search)
    t_rest, t_dyn = settings.tau_acc
    # bursts of linear acceleration make the accelerometer untrustworthy in motion: a longer τ (or off)
    assert 0 < t_rest and (t_dyn < 0 or t_dyn > t_rest)
    assert settings.bias_tau > 0  # a 0.5 °/s bias is worth learning at rest
    assert history[-1][2] < history[0][2]  # the objective only goes down
    fixed = TogglingSettings(states=("rest", "dynamic"), static_state="rest", tau_acc=(t_rest, t_rest),
                             tau_mag=settings.tau_mag, bias_tau=settings.bias_tau)
    assert mean_total_rmse(settings, trials, preds) < mean_total_rmse(fixed, trials, preds)


def test_parallel_objective_equals_serial():
    trials, preds = zip(*(make_trial(s) for s in (3, 4, 5)))
    search = GainSearch(tau=(33.33, 3.328), output_tau=(0.0,), bias_tau=(-1.0,), mag_disturbance_scale=(0.0,), sweeps=1)
    serial = learn_gains(trials, preds, ("rest", "dynamic"), "rest", search=search, memo=None)
    parallel = learn_gains(trials, preds, ("rest", "dynamic"), "rest", search=search, jobs=2, memo=None)
    assert serial == parallel  # same settings and the same objective values, bit for bit


def test_memo_gives_the_computed_values_and_is_keyed_on_content():
    trials, preds = zip(*(make_trial(s) for s in (3, 4)))
    # three sweeps: on these trials the first keeps a step in every coordinate (the second then tries new points
    # only), the second keeps none
    search = GainSearch(tau=(33.33, 3.328), output_tau=(0.0,), bias_tau=(-1.0,), mag_disturbance_scale=(0.0,), sweeps=3)
    plain = learn_gains(trials, preds, ("rest", "dynamic"), "rest", search=search, memo=None)
    memo = EvaluationMemo()
    first = learn_gains(trials, preds, ("rest", "dynamic"), "rest", search=search, memo=memo)
    # a sweep after one that kept no step re-tries the points of that sweep: those come from the memo
    assert first == plain and memo.hits > 0
    n_stored, hits = len(memo.values), memo.hits
    again = learn_gains(trials, preds, ("rest", "dynamic"), "rest", search=search, memo=memo)
    assert again == plain and len(memo.values) == n_stored and memo.hits > hits  # all from the memo, same floats
    # other content, other key: a changed prediction or signal is never served a stored value
    other = [p.copy() for p in preds]
    other[1][100, 0] = 0.5
    assert trials_digest(trials, other) != trials_digest(trials, preds)
    moved = [dataclasses.replace(trials[0], gyr=trials[0].gyr + 1e-12), trials[1]]
    assert trials_digest(moved, preds) != trials_digest(trials, preds)


def test_fused_objective_equals_broad_metric(rng):
    from togglecf.metrics.broad import trial_errors
    from togglecf.toggling.gains import _total_rmse_deg
    from conftest import random_quats
    q_ref = random_quats(rng, 3000)
    q_est = quat.multiply(quat.from_rotvec(0.05 * rng.standard_normal((3000, 3))), q_ref) * -2.0  # scaled, flipped
    q_ref[::17] = np.nan
    mov = rng.random(3000) > 0.3
    expected = trial_errors(q_est, q_ref, mov)["total"]
    assert _total_rmse_deg(q_est, q_ref, mov) == pytest.approx(expected, rel=1e-12)


def _disturbed(seed, eta_m):
    """``make_trial`` with a 20 µT offset in the sensor frame on the magnetometer for 10 s of the
    motion, and the regressors' output ``eta_m(true offset per sample)`` in the predictions."""
    t, pred = make_trial(seed)
    offset = np.zeros_like(t.mag)
    offset[2000:3000] = (20.0, -10.0, 5.0)
    t = dataclasses.replace(t, mag=t.mag + offset)
    pred[:, 5:8] = eta_m(offset)
    return t, pred


@pytest.mark.parametrize("regressor", ["right", "wrong"])
def test_noise_removal_is_learned_only_where_it_helps(regressor):
    """The descent starts with the noise regressors off (issue 12: a regressor that does not
    generalise must earn its weight on the training trials). A regressor that predicts the true
    disturbance gets weight 1; one that predicts a disturbance where there is none stays at 0."""
    eta = (lambda off: off) if regressor == "right" else (lambda off: np.roll(off, 1500, axis=0))  # 15 s late
    trials, preds = zip(*(_disturbed(s, eta) for s in (6, 7)))
    search = GainSearch(tau=(9.995,), output_tau=(0.0,), bias_tau=(-1.0,), mag_disturbance_scale=(0.0,),
                        noise_weight_acc=(0.0,), noise_weight_mag=(0.0, 1.0), sweeps=1)
    assert search.start(("rest", "dynamic"), "rest").noise_weight_mag == 0.0
    settings, _ = learn_gains(trials, preds, ("rest", "dynamic"), "rest", search=search)
    assert settings.noise_weight_mag == (1.0 if regressor == "right" else 0.0)
