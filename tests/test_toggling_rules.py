"""The toggling CF learns with the learned VQF's rules for learning that does no harm off its training
data: a step of its gain search is kept by the one-standard-error rule, σ_m is no smaller than a
consumer magnetometer's calibration residual, and its magnetometer back-off is bounded by the
rejection factor (the heading gain never below α_m / f_reject). Its heading correction's rate bound is
never below a consumer gyroscope's bias and acts as Madgwick's β does; its predicted field follows the
tilt correction, so a tilt step leaves the heading alone. A gyro bias left in motion is learned from the
heading correction where the field and the accelerometer pass their checks (step 5b)."""
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from togglecf import simulate as sim
from togglecf.core import quaternion as quat
from togglecf.filters.timeconst import gain
from togglecf.filters.toggling import TogglingFilter, TogglingSettings, rate_bounded_gain, turn_as
from togglecf.metrics.broad import error_angles_rad, error_quaternion
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


RATE_FLOOR = 0.02  # rad/s, about 1 °/s: a consumer gyroscope's bias, which the toggling CF learns fully only at rest


@pytest.mark.parametrize("which", ["config", "defaults"])
def test_the_heading_rate_bound_is_never_below_a_consumer_gyroscopes_bias(which):
    """A bound below the gyro bias left in motion cannot hold the heading against it: the grid has 0 (no
    bound) and values from 0.02 rad/s."""
    grid = _searches()[which].mag_rate_limit
    assert 0.0 in grid
    assert all(v == 0.0 or v >= RATE_FLOOR for v in grid), grid


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


# ---------------------------------------------------------------- the heading correction's rate bound

def _turn(v, w):
    """Angle [rad] between vectors v and w."""
    return float(np.arctan2(np.linalg.norm(np.cross(v, w)), np.dot(v, w)))


def test_the_rate_bound_turns_the_vector_by_at_most_its_angle_and_is_exact_at_it():
    """rate_bounded_gain on random vectors: the step (1 − α') v + α' m turns v by at most θ_max, by
    exactly θ_max where the bound lowers α (α' solves tan θ = α |v × m| / (v · v_new)), and leaves α
    unchanged where the step is smaller; 1e-12: float64 rounding of a few products."""
    rng = np.random.default_rng(0)
    theta = 0.05 * 0.01  # 0.05 rad/s at 100 Hz
    bounded = 0
    for _ in range(2000):
        v = rng.normal(size=3) * 40.0
        m = rng.normal(size=3) * rng.uniform(5.0, 80.0)
        alpha = 10.0 ** rng.uniform(-6.0, -1.3)
        a = rate_bounded_gain(alpha, v, m, np.tan(theta))
        turned = _turn(v, (1.0 - a) * v + a * m)
        assert 0.0 < a <= alpha
        assert turned <= theta * (1.0 + 1e-12)
        if a < alpha:
            bounded += 1
            assert turned == pytest.approx(theta, rel=1e-12)
        else:
            assert _turn(v, (1.0 - alpha) * v + alpha * m) <= theta * (1.0 + 1e-12)
    assert 100 < bounded < 1900  # both branches were exercised
    assert rate_bounded_gain(0.3, np.array([1.0, 0, 0]), np.array([0, 1.0, 0]), 0.0) == 0.3  # 0: no bound


def _turned_field(duration, **settings):
    """A sensor at rest whose field turns by 90° in azimuth at 1 s (a disturbance that stays): the truth ``(N, 4)``,
    the trial, and a toggling CF with τ 3.5 s, no bias learned at rest, and ``settings``."""
    n = int(duration * FS)
    q = np.tile(quat.IDENTITY, (n, 1))
    turned = sim.EARTH_MAG_ENU[[1, 0, 2]] * np.array([-1.0, 1.0, 1.0])  # azimuth +90°: north -> west
    dist = np.zeros((n, 3))
    dist[int(FS):] = turned - sim.EARTH_MAG_ENU
    trial = sim.imu_from_orientation(q, FS, mag_disturbance_earth=dist)
    s = TogglingSettings(tau_acc=(3.498, 3.498), tau_mag=(3.498, 3.498), bias_tau=-1.0, noise_weight_acc=0.0,
                         noise_weight_mag=0.0, **settings)
    return q, trial, TogglingFilter(FS, settings=s)


def _turned_field_run(mag_rate_limit, duration=30.0):
    """``_turned_field`` sample by sample: the output's rotation from the truth [rad] (the heading error; no tilt
    error) and the angle [rad] by which each sample's step turned m_pred."""
    # the heading bias off: a field turned in azimuth keeps its norm and dip, passes step 5b's check, and the
    # bias it feeds would turn m_pred through the gyro as well
    # (test_a_field_turned_in_azimuth_feeds_the_bias_for_a_while)
    q, trial, f = _turned_field(duration, mag_rate_limit=mag_rate_limit, heading_bias_tau=0.0)
    n = len(q)
    out, step = np.empty((n, 4)), np.zeros(n)
    m_before = None
    for i in range(n):
        out[i] = f.update(trial.gyr[i], trial.acc[i], trial.mag[i])
        d = f.state_dict()
        m_pred = np.array([d["m_pred_x"], d["m_pred_y"], d["m_pred_z"]])
        if m_before is not None:
            step[i] = _turn(m_before, m_pred)
        m_before = m_pred
    return quat.angle_between(out, q), step


def test_a_disturbance_turns_the_heading_no_faster_than_the_bound():
    """With ω_m = 0.05 rad/s no step turns m_pred by more than ω_m Ts (the sensor is at rest: only the
    correction turns it; 1e-9 for rounding), the heading follows the turned field far more slowly than
    with τ_mag 3.5 s alone, and in the end it still gets there."""
    limit = 0.05
    bounded, step = _turned_field_run(limit)
    free, free_step = _turned_field_run(0.0)
    assert step.max() <= limit / FS * (1.0 + 1e-9)
    assert free_step.max() > 2.0 * limit / FS  # without the bound the first steps are about 3x larger
    assert free[int(3 * FS)] > 0.35 * np.pi / 2  # 2 s of τ 3.5 s: about 43 % of the 90°
    assert bounded[int(3 * FS)] < 0.15 * np.pi / 2
    assert bounded[-1] == pytest.approx(np.pi / 2, abs=np.radians(1.0))


def test_the_rate_bound_is_checked_and_off_by_default():
    assert TogglingSettings().mag_rate_limit == 0.0
    assert GainSearch().start(("rest", "dynamic"), "rest").mag_rate_limit == 0.0  # the descent starts without it
    for bad in (-0.1, float("inf"), float("nan")):
        with pytest.raises(ValueError, match="mag_rate_limit"):
            TogglingSettings(mag_rate_limit=bad)


# ---------------------------------------------------------------- the field follows the tilt correction

def _tuples(*vectors):
    """Each vector as a tuple of floats: ``turn_as`` is compiled for the filter's tuples, one type for all three."""
    return tuple(tuple(float(x) for x in v) for v in vectors)


def test_turn_as_is_the_shortest_arc_rotation_between_two_directions():
    """``turn_as(u, v, w)`` against scipy: with R a rotation by less than 90° about an axis normal to u,
    and v = R u at any length, R w (1e-12: float64 rounding); u itself goes to v's direction; w stays
    where u or v is zero or they are 90° or more apart."""
    rng = np.random.default_rng(1)
    for _ in range(200):
        u, w = rng.normal(size=3) * rng.uniform(0.1, 20.0), rng.normal(size=3) * 40.0
        axis = np.cross(u, rng.normal(size=3))
        rot = Rotation.from_rotvec(axis / np.linalg.norm(axis) * rng.uniform(0.0, 0.49 * np.pi))
        v = rot.apply(u) * rng.uniform(0.1, 10.0)
        np.testing.assert_allclose(turn_as(*_tuples(u, v, w)), rot.apply(w), rtol=0, atol=1e-12 * np.linalg.norm(w))
        turned = np.array(turn_as(*_tuples(u, v, u)))
        np.testing.assert_allclose(turned / np.linalg.norm(turned), v / np.linalg.norm(v), atol=1e-12)
    w = (1.0, 2.0, 3.0)
    for u, v in (((0.0, 0.0, 0.0), (1.0, 0.0, 0.0)), ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0)),
                 ((1.0, 0.0, 0.0), (-1.0, 0.1, 0.0)), ((1.0, 0.0, 0.0), (np.nan, 0.0, 0.0))):
        assert turn_as(u, v, w) == w


def _linear_acceleration_run():
    """A sensor at rest at the identity in an undisturbed field, with a constant 2 m/s² linear acceleration
    along east from 1 s to 5 s (the accelerometer's tilt is then 11.5° off): BROAD's heading and
    inclination errors [rad] per sample of the toggling CF (τ_acc 1 s, no heading correction: τ_mag < 0; no
    bias estimate, no gyro noise)."""
    n = int(5.0 * FS)
    acc = np.tile([0.0, 0.0, sim.GRAVITY], (n, 1))
    acc[int(FS):, 0] = 2.0
    mag = np.tile(sim.EARTH_MAG_ENU, (n, 1))
    s = TogglingSettings(tau_acc=(1.0, 1.0), tau_mag=(-1.0, -1.0), bias_tau=-1.0, noise_weight_acc=0.0,
                         noise_weight_mag=0.0)
    q = TogglingFilter(FS, settings=s).update_batch(np.zeros((n, 3)), acc, mag).quat
    return error_angles_rad(error_quaternion(q, np.tile(quat.IDENTITY, (n, 1))))


def test_a_tilt_correction_turns_the_field_with_it_and_leaves_the_heading():
    """The accelerometer pulls the tilt 11.5° off (a linear acceleration taken for gravity); with no
    heading correction m_pred turns with a_pred, so the output turns about a horizontal axis
    only: BROAD's heading error stays 0 (1e-9 rad: float64 rounding over 500 steps). Without the follow
    it would be about tan(67°) × the tilt error here (the field's dip), some 25°."""
    err = _linear_acceleration_run()
    assert err["inclination"][-1] > np.radians(10.0)  # the tilt did move: 11.5° × (1 − e⁻⁴)
    assert np.max(err["heading"]) < 1e-9


# ---------------------------------------------------------------- step 5b: the heading bias in motion

BIAS_Z = np.radians(0.5)  # rad/s about the vertical, a consumer gyroscope's bias after turn-on
TAU_MAG = 3.498


def _heading_bias_run(duration=300.0, heading_bias_tau=30.0, lin_acc=None, disturbance=None, bias=BIAS_Z, **kw):
    """A level sensor turning slowly about the vertical (0.2 rad/s, so step 1's gate (0.05 rad/s) never takes
    it as rest) with a gyro bias ``bias`` [rad/s] about z; no noise. Returns the heading error [rad] per
    sample (the output's rotation from the truth, no tilt error here) and the filter."""
    n = int(duration * FS)
    t = np.arange(n) / FS
    q = quat.from_rotvec(np.outer(0.2 * t, [0.0, 0.0, 1.0]))
    trial = sim.imu_from_orientation(q, FS, gyro_bias=(0.0, 0.0, bias), lin_acc_earth=lin_acc,
                                     mag_disturbance_earth=disturbance)
    s = TogglingSettings(tau_acc=(3.498, 3.498), tau_mag=(TAU_MAG, TAU_MAG), bias_tau=-1.0, noise_weight_acc=0.0,
                         noise_weight_mag=0.0, heading_bias_tau=heading_bias_tau, **kw)
    f = TogglingFilter(FS, settings=s)
    out = f.update_batch(trial.gyr, trial.acc, trial.mag).quat
    return quat.angle_between(out, q), f


def test_a_bias_in_motion_is_learned_from_the_heading_correction():
    """Without step 5b the heading lags by bias × τ_mag (a first-order loop's steady error: 0.5 °/s × 3.5 s =
    1.75°; 5 % for the output's γ and sin vs angle); with it the PI loop (ζ = ½ √(30 / 3.5) ≈ 1.5: two real
    poles, time constants about 4 s and 26 s) removes it: after 300 s (11 slow time constants) the bias is
    learned to 1 % and the heading error is below 0.02°."""
    off, f_off = _heading_bias_run(heading_bias_tau=0.0)
    assert np.degrees(off[-1]) == pytest.approx(np.degrees(BIAS_Z) * TAU_MAG, rel=0.05)
    assert f_off.state_dict()["bias_z"] == 0.0
    on, f_on = _heading_bias_run()
    assert np.degrees(on[-1]) < 0.02
    d = f_on.state_dict()
    assert d["bias_z"] == pytest.approx(BIAS_Z, rel=0.01)
    assert abs(d["bias_x"]) + abs(d["bias_y"]) < 1e-6 * BIAS_Z  # fed about the vertical only
    # the field reference is the earth's (simulate.EARTH_MAG_ENU): norm [µT] and dip [rad] (positive: it points down)
    assert d["mag_ref_norm"] == pytest.approx(np.linalg.norm(sim.EARTH_MAG_ENU), rel=1e-9)
    assert d["mag_ref_dip"] == pytest.approx(np.arcsin(-sim.EARTH_MAG_ENU[2] / np.linalg.norm(sim.EARTH_MAG_ENU)),
                                             abs=1e-9)
    assert d["mag_ref_dip"] > 0.0


@pytest.mark.parametrize("what", ["field norm", "field dip", "acceleration"])
def test_no_heading_bias_is_fed_while_a_check_fails(what):
    """A field 30 % stronger (check: 10 %), a field whose dip moves by 20° (check: 10°) from the second sample on,
    or a horizontal acceleration of 0.5 g all along (|a| 12 % above g; check: 10 %): the bias stays at zero and
    the heading keeps the first-order lag (so what fed it in the test above was step 5b, not step 1)."""
    n = int(60.0 * FS)
    lin_acc = disturbance = None
    if what == "field norm":
        disturbance = np.tile(0.3 * sim.EARTH_MAG_ENU, (n, 1))
        disturbance[0] = 0.0  # the reference is set from the first sample, undisturbed
    elif what == "field dip":  # turn the field about east by 20° from the start on: its norm unchanged
        disturbance = np.tile(Rotation.from_euler("x", 20, degrees=True).apply(sim.EARTH_MAG_ENU)
                              - sim.EARTH_MAG_ENU, (n, 1))
        disturbance[0] = 0.0  # the reference is set from the first sample, undisturbed
    else:
        lin_acc = np.tile([0.5 * 9.81, 0.0, 0.0], (n, 1))
    err, f = _heading_bias_run(duration=60.0, lin_acc=lin_acc, disturbance=disturbance)
    d = f.state_dict()
    assert d["bias_x"] == d["bias_y"] == d["bias_z"] == 0.0
    if what != "acceleration":  # (under the acceleration the tilt is off too)
        assert np.degrees(err[-1]) == pytest.approx(np.degrees(BIAS_Z) * TAU_MAG, rel=0.05)


def test_the_heading_bias_feed_is_clipped():
    """A bias of 5 °/s is more than the feed may learn: it stops at heading_bias_clip (2 °/s), to a part in 1e3
    (it stops one increment short at most, and one increment, sin θ_h / τ_i with θ_h one sample's heading
    correction, is far smaller)."""
    _, f = _heading_bias_run(duration=120.0, bias=np.radians(5.0))
    d = f.state_dict()
    learned = np.hypot(np.hypot(d["bias_x"], d["bias_y"]), d["bias_z"])
    assert learned <= TogglingSettings().heading_bias_clip
    assert learned == pytest.approx(TogglingSettings().heading_bias_clip, rel=1e-3)


def test_the_heading_bias_settings_are_checked():
    assert TogglingSettings().heading_bias_tau == 30.0
    assert TogglingSettings().heading_bias_clip == pytest.approx(np.radians(2.0), rel=1e-5)
    for name in ("heading_bias_tau", "heading_bias_clip", "mag_norm_threshold", "mag_dip_threshold", "mag_ref_tau",
                 "acc_norm_threshold"):
        for bad in (-0.1, float("inf"), float("nan")):
            with pytest.raises(ValueError, match=name):
                TogglingSettings(**{name: bad})


def test_a_field_turned_in_azimuth_feeds_the_bias_for_a_while():
    """What step 5b's checks cannot see: a field turned by 90° in azimuth keeps its norm and dip. The heading
    correction then feeds the bias, up to the clip (2 °/s), and the heading overshoots; with no true bias the PI
    loop unlearns it as the heading settles: after 600 s (about 20 of its slow time constants of 26 s) the bias
    is below 1e-7 °/s and the heading has followed the field to 1e-5°."""
    q, trial, f = _turned_field(600.0)
    out = f.update_batch(trial.gyr, trial.acc, trial.mag)
    bias = out.diagnostics["bias_norm"]
    clip = TogglingSettings().heading_bias_clip
    assert bias.max() <= clip and bias.max() == pytest.approx(clip, rel=1e-3)
    assert np.degrees(quat.angle_between(out.quat, q)).max() > 91.0  # the overshoot
    assert np.degrees(bias[-1]) < 1e-7
    assert np.degrees(quat.angle_between(out.quat[-1:], q[-1:]))[0] == pytest.approx(90.0, abs=1e-5)
