"""The one bad-sample policy of ``filters.base`` for a saturated gyro: a reading with an axis at or
beyond ``GYRO_FULL_SCALE`` is not integrated. Every filter must then end the sample exactly where
it ends when that sample's gyro is absent (NaN), with everything else (acc, mag, Δt, state)
the same. Per filter that means:

* gyro:     orientation unchanged.
* accmag:   the gyro is never used: the same as with any gyro reading (e.g. zero).
* cf:       no propagation; the acc/mag blend still runs.
* madgwick: ω = 0 for the sample (the same as a zero reading); the gradient step still runs.
* mahony:   ω_y − b̂ = 0 (the same as a reading equal to the bias estimate b̂); the
            correction and the integral (bias) update still run.
* aqua:     no prediction, no bias update, the reading is not kept as the previous ω; the
            acc/mag corrections still run.
* ekf:      no propagation (κ = 0 in the process noise); the measurement updates still run.
* toggling: no propagation, no bias learning; the vector CF and the blend still run.
* any other registered filter (e.g. vqf_core): the general check only.

The saturation test is on the raw reading: a filter with a bias estimate b̂ must not let
ω − b̂ slip back under full scale (hence the tests run with a non-zero bias).
"""
import numpy as np
import pytest

from togglecf.filters import FILTERS
from togglecf.filters.base import GYRO_FULL_SCALE, N_COMMON_STATE
from togglecf.filters.toggling import TogglingFilter

FS = 285.714
CLASSES = {**FILTERS, "toggling": TogglingFilter}
BIAS = np.array([0.2, -0.15, 0.1])  # rad/s: enough to take 34.95 − 0.2 under full scale
SATURATED = {
    "x_just_over": [GYRO_FULL_SCALE + 0.05, 0.1, -0.2],
    "at_full_scale": [0.3, -GYRO_FULL_SCALE, 0.1],
    "all_axes": [35.0, -35.0, 35.0],
    "far_beyond": [-100.0, 0.0, 0.0],
}


def _warm(name, use_mag):
    """A filter after 300 samples of smooth simulated motion, its bias (if any) set to BIAS."""
    f = CLASSES[name](FS, use_mag=use_mag)
    k = np.arange(300)[:, None] / FS
    gyr = np.hstack([0.4 * np.sin(2 * k), 0.3 * np.cos(3 * k), 0.2 + 0 * k])
    acc = np.hstack([0.5 + 0.1 * np.sin(k), 0.2 + 0 * k, 9.78 + 0 * k])
    mag = np.hstack([3.0 + 0 * k, 19.0 + np.cos(k), -42.0 + 0 * k])
    f.update_batch(gyr, acc, mag if use_mag else None)
    if "bias_x" in f.state_names:
        i = N_COMMON_STATE + f.state_names.index("bias_x")
        f.state[i:i + 3] = BIAS
    return f


def _one(f, state, gyr):
    """State and diagnostics after one sample with ``gyr`` from ``state`` (fixed acc, mag, Δt)."""
    f.set_state(state)
    f.update(np.asarray(gyr, float), [0.6, 0.1, 9.75], [3.5, 18.0, -41.0] if f.use_mag else None)
    return f.get_state(), f._diag.copy()


def _same(a, b):
    return np.array_equal(a[0], b[0], equal_nan=True) and np.array_equal(a[1], b[1], equal_nan=True)


@pytest.mark.parametrize("sat", list(SATURATED), ids=list(SATURATED))
@pytest.mark.parametrize("use_mag", [True, False], ids=["9D", "6D"])
@pytest.mark.parametrize("name", sorted(CLASSES))
def test_saturated_gyro_is_as_if_absent(name, use_mag, sat):
    f = _warm(name, use_mag)
    s0 = f.get_state()
    got = _one(f, s0, SATURATED[sat])
    absent = _one(f, s0, [np.nan, np.nan, np.nan])
    assert _same(got, absent), f"{name}: a saturated gyro sample is not treated like a missing one"
    # the per-filter meaning of "absent" (module docstring)
    if name == "gyro":
        assert np.array_equal(got[0][:4], s0[:4])
    if name in ("accmag", "madgwick"):
        assert _same(got, _one(f, s0, [0.0, 0.0, 0.0]))
    if name == "mahony":
        i = N_COMMON_STATE + f.state_names.index("bias_x")
        assert _same(got, _one(f, s0, s0[i:i + 3]))
    if name in ("aqua", "toggling"):  # their bias is learned from the gyro reading alone
        i = N_COMMON_STATE + f.state_names.index("bias_x")
        assert np.array_equal(got[0][i:i + 3], BIAS)


@pytest.mark.parametrize("use_mag", [True, False], ids=["9D", "6D"])
@pytest.mark.parametrize("name", sorted(CLASSES))
def test_reading_just_below_full_scale_is_integrated(name, use_mag):
    """The counterpart: a large but valid rate is integrated (so the test above is not vacuous)."""
    f = _warm(name, use_mag)
    s0 = f.get_state()
    got = _one(f, s0, [GYRO_FULL_SCALE - 0.05, 0.1, -0.2])
    absent = _one(f, s0, [np.nan, np.nan, np.nan])
    if name == "accmag":
        assert _same(got, absent)
    else:
        assert not np.array_equal(got[0][:4], absent[0][:4])
