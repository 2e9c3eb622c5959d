"""Issue 12, item 1: every gain of the CF, AQUA and the toggling CF is a time constant [s],
converted per sample from the filter's nominal Ts (k = 1 − exp(−Ts/τ)).

(a) at BROAD's 285.714 Hz the new defaults and grids give the former per-sample coefficients
    (< 1e-3 relative); (b) the same settings at 100 Hz and 300 Hz: a tilt step decays with the
    same time constant in seconds, and the errors on the same simulated motion agree; (c) a
    ``gains.json`` of the old format (per-sample gains, no ``format`` key) is refused.
"""
import json
import math
import tomllib
from importlib.resources import files

import numpy as np
import pytest

from togglecf import simulate as sim
from togglecf.core import quaternion as quat
from togglecf.filters.aqua import AquaFilter
from togglecf.filters.complementary import ComplementaryFilter
from togglecf.filters.timeconst import BROAD_FS, gain, tau_from_gain
from togglecf.filters.toggling import TogglingFilter
from togglecf.metrics.broad import trial_errors
from togglecf.toggling.gains import GAINS_FORMAT, GainSearch, load_gains

TS = 1.0 / BROAD_FS
OLD_GRID = (0.0, 0.00003, 0.0001, 0.0002, 0.0005, 0.001, 0.002, 0.005, 0.01, 0.02, 0.05)


def rel(a, b):
    return abs(a / b - 1.0) if b else abs(a)


# ------------------------------------------------------------------ (a) the former numbers at 285.7 Hz

def test_conversion_helpers():
    assert gain(-1.0, TS) == 0.0 and gain(0.0, TS) == 1.0
    assert gain(12.5, TS) == pytest.approx(1 - math.exp(-TS / 12.5), rel=1e-15)
    for a in (1e-5, 0.00028, 0.01, 0.5):
        assert gain(tau_from_gain(a, TS), TS) == pytest.approx(a, rel=1e-12)
    assert tau_from_gain(0.0) == -1.0 and tau_from_gain(1.0) == 0.0


def test_defaults_reproduce_the_former_per_sample_coefficients_at_broad_rate():
    cf = ComplementaryFilter(BROAD_FS).params
    aq = AquaFilter(BROAD_FS).params
    tg = TogglingFilter(BROAD_FS).params
    pairs = [(cf.alpha, 0.00028), (aq.gain_acc, 0.0003), (aq.gain_mag, 0.00005), (aq.bias_alpha, 0.002),
             (tg.alpha_acc[0], 0.01), (tg.alpha_acc[1], 0.0005), (tg.alpha_mag[0], 0.002),
             (tg.alpha_mag[1], 0.0005), (tg.bias_gain, 0.002), (tg.gamma, 1.0)]
    for new, old in pairs:
        assert rel(new, old) < 1e-3, (new, old)


def test_search_grids_are_the_former_points_at_broad_rate():
    s = GainSearch()
    for new, old in zip(s.tau, OLD_GRID, strict=True):
        assert rel(gain(new, TS), old) < 1e-3
    for new, old in zip(s.bias_tau, (0.0, 0.0003, 0.001, 0.003), strict=True):
        assert rel(gain(new, TS), old) < 1e-3
    for new, old in zip(s.output_tau, (0.3, 0.6, 1.0), strict=True):
        assert rel(gain(new, TS), old) < 1e-3
    start = s.start(("a", "b"), "a")
    assert rel(gain(start.tau_acc[0], TS), 0.001) < 1e-3 and rel(gain(start.tau_mag[0], TS), 0.0003) < 1e-3


def test_config_grids_are_the_former_points_at_broad_rate():
    cfg = files("togglecf.configs")
    g = tomllib.loads(cfg.joinpath("default.toml").read_text())["gains"]
    old = {"tau": (0.00005, 0.0001, 0.0002, 0.0005, 0.001, 0.002, 0.005), "output_tau": (0.5, 1.0),
           "bias_tau": (0.0, 0.0003, 0.001, 0.003)}
    study = tomllib.loads(cfg.joinpath("study.toml").read_text())
    old_cf = tuple(0.0001 + 0.00005 * i for i in range(11))  # "0.0001:0.0006:0.00005"
    checks = [(g[k], v) for k, v in old.items()] + [
        (study["baselines"]["cf"]["tau"], old_cf), (study["baselines_6d"]["cf"]["tau"], old_cf),
        (study["baselines"]["aqua"]["tau_acc"], (0.0001, 0.0002, 0.0003, 0.0005, 0.001)),
        (study["baselines"]["aqua"]["tau_mag"], (0.00002, 0.00005, 0.0001, 0.0002))]
    for taus, alphas in checks:
        assert len(taus) == len(alphas)
        for t, a in zip(taus, alphas):
            assert rel(gain(t, TS), a) < 1e-3, (t, a)


# ------------------------------------------------------------------------- (b) rate independence

STEP_TAU = 2.0


def _tilt_step(make, fs, duration=8.0):
    """Tilt error [deg] per sample after starting 10° off, at rest, noise-free (6D)."""
    n = int(round(duration * fs))
    q_true = sim.static_trajectory([0, 0, 30], n)
    tr = sim.imu_from_orientation(q_true, fs)
    f = make(fs)
    f.set_quat(quat.multiply(quat.from_rotvec(np.radians([10.0, 0.0, 0.0])), q_true[0]))
    if isinstance(f, TogglingFilter):
        # the vector CF starts from the gravity predicted by the wrong orientation
        f.state[8:11] = quat.rotate(quat.conjugate(f.state[:4]), [0.0, 0.0, 9.81])
        pred = np.zeros((n, 8))
        pred[:, 0] = 1.0
        q = f.update_batch(tr.gyr, tr.acc, None, predictions=pred).quat
    else:
        q = f.update_batch(tr.gyr, tr.acc, None).quat
    return np.arange(1, n + 1) / fs, np.degrees(quat.angle_between(q, q_true))


STEP_FILTERS = {
    "cf": lambda fs: ComplementaryFilter(fs, tau=STEP_TAU, use_mag=False),
    "aqua": lambda fs: AquaFilter(fs, tau_acc=STEP_TAU, adaptive=False, estimate_bias=False, use_mag=False),
    "toggling": lambda fs: TogglingFilter(fs, tau_acc=(STEP_TAU, 50.0), bias_tau=-1.0, use_mag=False),
}


def fitted_tau(t, e):
    """Time constant [s] of an exponential decay: slope of log(e) between 10 % and 90 % of the run."""
    sel = (t > 0.1 * t[-1]) & (t < 0.9 * t[-1])
    return -1.0 / np.polyfit(t[sel], np.log(e[sel]), 1)[0]


@pytest.mark.parametrize("name", list(STEP_FILTERS))
def test_step_response_has_the_same_time_constant_in_seconds_at_100_and_300_hz(name):
    taus = {}
    for fs in (100.0, 300.0):
        t, e = _tilt_step(STEP_FILTERS[name], fs)
        assert e[0] > 9.0
        taus[fs] = fitted_tau(t, e)
    # the tilt error decays as exp(−t/τ): the same τ in seconds at both rates
    assert taus[100.0] == pytest.approx(STEP_TAU, rel=0.01) and taus[300.0] == pytest.approx(STEP_TAU, rel=0.01)
    assert taus[100.0] == pytest.approx(taus[300.0], rel=0.005), taus


DURATION = 90.0
REST_S = 15.0
#: relative tolerance of the total RMSE at 100 Hz vs 300 Hz (measured: <= 3 %; per-sample gains: x1.5-2)
RATE_RTOL = 0.10


def _motion_trial(fs):
    """The same motion at any rate: 15 s at rest, then a slow three-axis gimbal motion with bursts of
    linear acceleration; a constant gyro bias and small white noise."""
    n_rest = int(round(REST_S * fs))
    move = sim.gimbal_trajectory(fs, DURATION - REST_S)
    q = np.vstack([np.repeat(move[:1], n_rest, axis=0), move])
    n = len(q)
    lin = sim.linear_acceleration_bursts(n, fs, ((30.0, 2.0, (2.0, 0.0, 0.0)), (55.0, 2.0, (0.0, -2.0, 0.0))))
    tr = sim.imu_from_orientation(q, fs, gyro_noise=0.002, acc_noise=0.02, mag_noise=0.2,
                                  gyro_bias=(0.004, -0.006, 0.003), lin_acc_earth=lin, seed=3)
    rest = np.arange(n) < n_rest
    return tr, rest


def _run(name, fs, settings):
    tr, rest = _motion_trial(fs)
    if name == "toggling":
        pred = np.zeros((len(rest), 8))
        pred[rest, 0] = 1.0
        pred[~rest, 1] = 1.0
        q = TogglingFilter(fs, **settings).update_batch(tr.gyr, tr.acc, tr.mag, predictions=pred).quat
    else:
        cls = {"cf": ComplementaryFilter, "aqua": AquaFilter}[name]
        q = cls(fs, **settings).update_batch(tr.gyr, tr.acc, tr.mag).quat
    return trial_errors(q, tr.opt_quat, np.arange(len(q)) > 5 * fs)["total"]


RATE_SETTINGS = {"cf": dict(tau=3.0), "aqua": dict(tau_acc=3.0, tau_mag=10.0),
                 "toggling": dict(tau_acc=(0.5, 5.0), tau_mag=(2.0, 10.0), bias_tau=1.0)}


@pytest.mark.parametrize("name", list(RATE_SETTINGS))
def test_same_settings_give_the_same_error_at_100_and_300_hz(name):
    e100, e300 = _run(name, 100.0, RATE_SETTINGS[name]), _run(name, 300.0, RATE_SETTINGS[name])
    assert e100 < 5.0 and e300 < 5.0
    assert e100 == pytest.approx(e300, rel=RATE_RTOL), (e100, e300)


# ------------------------------------------------------------------------ (c) the old format

def _model_dir(tmp_path, gains_doc):
    d = tmp_path / "old_models"
    d.mkdir(parents=True)
    (d / "metadata.json").write_text(json.dumps({"feature_schema": {"hash": "abc"}}))
    (d / "gains.json").write_text(json.dumps(gains_doc))
    return d


def test_old_format_gains_are_refused_with_a_message_to_retrain(tmp_path):
    old = {"feature_schema_hash": "abc",
           "9d": {"filter": "toggling", "settings": {"states": ["static", "dynamic"], "alpha_acc": [0.01, 0.0005],
                                                    "alpha_mag": [0.002, 0.0005], "gamma": 1.0,
                                                    "bias_gain": 0.002}}}
    d = _model_dir(tmp_path, old)
    with pytest.raises(ValueError) as exc:
        load_gains(d)
    msg = str(exc.value)
    assert str(d / "gains.json") in msg and "old format" in msg and "`togglecf train`" in msg
    with pytest.raises(ValueError, match="has format 1"):  # an explicit other format, too
        load_gains(_model_dir(tmp_path / "x", {**old, "format": 1}))


def test_new_format_round_trip_records_the_training_rate(tmp_path):
    from togglecf.filters.toggling import TogglingSettings
    from togglecf.toggling.gains import save_gains

    d = _model_dir(tmp_path, {})
    (d / "gains.json").unlink()
    settings = TogglingSettings(tau_acc=(0.5, 5.0), tau_mag=(2.0, 10.0), bias_tau=-1.0)
    tr = sim.imu_from_orientation(sim.static_trajectory([0, 0, 0], 10), BROAD_FS)
    save_gains(d, settings, [tr], [("start", None, 1.0)], use_mag=True)
    doc = json.loads((d / "gains.json").read_text())
    assert doc["format"] == GAINS_FORMAT == 2 and doc["trained_fs"] == [BROAD_FS] == doc["9d"]["trained_fs"]
    assert load_gains(d) == settings
