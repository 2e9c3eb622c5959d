"""The toggling CF learns with the learned VQF's rules for learning that does no harm off its training
data: a step of its gain search is kept by the one-standard-error rule, σ_m is no smaller than a
consumer magnetometer's calibration residual, and its magnetometer back-off is bounded by the
rejection factor (the heading gain never below α_m / f_reject)."""
import numpy as np
import pytest

from togglecf import simulate as sim
from togglecf.core import quaternion as quat
from togglecf.filters.timeconst import gain
from togglecf.filters.toggling import TogglingFilter, TogglingSettings
from togglecf.run.config import GAIN_KEYS, load_config
from togglecf.toggling.gains import GainSearch, VQFGainSearch

FS = 100.0
SIGMA_FLOOR = 10.0  # µT: a consumer magnetometer's calibration residual is a few µT


def _searches():
    g = load_config()["gains"]
    return {"config": GainSearch.from_dict({k: v for k, v in g.items() if k not in GAIN_KEYS}),
            "defaults": GainSearch(), "vqf_config": VQFGainSearch.from_dict(g.get("vqf", {}))}


@pytest.mark.parametrize("which", ["config", "defaults", "vqf_config"])
def test_both_searches_keep_a_step_by_one_standard_error_and_sigma_m_from_10_uT(which):
    search = _searches()[which]
    assert search.step_rule == "one_se"
    assert search.objective == "worst_dataset_log_ratio"
    assert all(s == 0.0 or s >= SIGMA_FLOOR for s in search.mag_disturbance_scale), search.mag_disturbance_scale
    assert 0.0 in search.mag_disturbance_scale  # the back-off can stay off


def test_the_search_starts_with_the_back_off_off_and_bounded():
    start = GainSearch().start(("rest", "dynamic"), "rest")
    assert start.mag_disturbance_scale == 0.0
    assert start.mag_rejection_factor == 2.0  # the VQF core's rejection factor


def _disturbed_run(f_reject, sigma_m=SIGMA_FLOOR, field=50.0):
    """A 30 s random motion at 100 Hz with a ``field`` [µT] disturbance from 10 s to 20 s, predicted
    exactly (η̂_m the disturbance in the sensor frame); returns the gains α_m used and the state's α_m."""
    q = sim.random_smooth_trajectory(FS, 30.0, max_rate=1.0, seed=3)
    dist = sim.mag_disturbance_intervals(len(q), FS, ((10.0, 20.0, (field, 0.0, 0.0)),))
    trial = sim.imu_from_orientation(q, FS, mag_disturbance_earth=dist, gyro_noise=0.002, acc_noise=0.03,
                                     mag_noise=0.3, seed=3)
    pred = np.zeros((len(q), 8))
    pred[:, 0] = 1.0
    pred[:, 5:8] = quat.rotate(quat.conjugate(q), dist)  # ENU -> sensor
    s = TogglingSettings(tau_acc=(3.498, 3.498), tau_mag=(3.498, 3.498), bias_tau=-1.0, noise_weight_acc=0.0,
                         noise_weight_mag=0.0, mag_disturbance_scale=sigma_m, mag_rejection_factor=f_reject)
    out = TogglingFilter(FS, settings=s).update_batch(trial.gyr, trial.acc, trial.mag, predictions=pred)
    t = np.arange(len(q)) / FS
    return out.diagnostics["alpha_mag"], gain(3.498, 1.0 / FS), (t >= 10.0) & (t < 20.0)


@pytest.mark.parametrize("f_reject", [1.0, 2.0, 4.0])
def test_the_back_off_slows_the_heading_gain_by_at_most_the_rejection_factor(f_reject):
    """(|η̂_m| / σ_m)² = 25 in the disturbance: the back-off is capped at f_reject (1: off); outside it
    the gain is the state's own."""
    alpha_m, alpha, inside = _disturbed_run(f_reject)
    used = alpha_m > 0.0  # 0: the first sample (initialisation)
    assert np.all(alpha_m[used] >= alpha / f_reject * (1 - 1e-12))
    np.testing.assert_allclose(alpha_m[inside], alpha / f_reject, rtol=1e-12)
    np.testing.assert_allclose(alpha_m[used & ~inside], alpha, rtol=1e-12)


def test_a_disturbance_below_the_bound_backs_off_as_before():
    """|η̂_m| = 5 µT, σ_m 10 µT: e = 0.25 < f_reject − 1, the back-off 1 + e as without the bound."""
    alpha_m, alpha, inside = _disturbed_run(2.0, field=5.0)
    np.testing.assert_allclose(alpha_m[inside], alpha / 1.25, rtol=1e-9)


def test_the_rejection_factor_is_checked():
    for bad in (0.5, float("inf"), float("nan")):
        with pytest.raises(ValueError, match="mag_rejection_factor"):
            TogglingSettings(mag_rejection_factor=bad)
