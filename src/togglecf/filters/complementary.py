"""Fixed-gain quaternion complementary filter.

Per sample (``Ts`` or the given Δt):

1. gyro propagation           q_g  = q ⊗ exp(ω Δt / 2)
2. acc/mag orientation        q_am = from_acc_mag(a, m)      (6D: a + predicted north)
3. complementary blend (LERP) q    = normalize((1 − α) q_g + α q_am),  q_am on q_g's hemisphere

α is the weight of the acc/mag measurement per sample; the time constant of the correction
is about ``Ts / α`` (α = 0.00028 at 285.7 Hz: ~12.5 s).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

from numba import njit

from togglecf.core.quaternion import normalize_scalar
from togglecf.filters.base import (
    FilterSettings,
    OrientationFilter,
    acc_mag_quaternion,
    initialize_from_sample,
    load_quat,
    propagate_gyro,
    store_quat,
    vector_ok,
)

__all__ = ["CFSettings", "ComplementaryFilter"]


@dataclass(frozen=True)
class CFSettings(FilterSettings):
    """Attributes:
        alpha: weight of the acc/mag orientation per sample, in [0, 1]. Default 0.00028, the
            TAGP over the 25 BROAD trials in shared/ (9D, 285.7 Hz; coarse grid 0.00002..0.05,
            then 0.0002:0.0004:0.00002): mean total RMSE 10.421°. Small, because this IMU's gyro biases (0.2-0.5 °/s) and
            up to ~2 m/s² of linear acceleration pull in opposite directions.
    """

    alpha: float = 0.00028

    def __post_init__(self):
        super().__post_init__()
        if not 0.0 <= self.alpha <= 1.0:
            raise ValueError(f"alpha must be in [0, 1], got {self.alpha}")


class CFCoefficients(NamedTuple):
    """``params`` of ``cf_step``: the common ``use_mag``, ``max_dt`` (see ``filters.base``), then
    ``alpha``, the weight of the acc/mag orientation per sample (``CFSettings.alpha``)."""

    use_mag: float
    max_dt: float
    alpha: float


@njit(cache=True)
def cf_step(state, params, gyr, acc, mag, dt, diag):
    """One sample of the fixed-gain CF (see module docstring). diag: [alpha used, mag used]."""
    use_mag, max_dt, alpha = params.use_mag > 0.5, params.max_dt, params.alpha
    acc_ok = vector_ok(acc)
    mag_ok = use_mag and vector_ok(mag)
    diag[0] = 0.0
    diag[1] = 0.0
    if state[4] < 0.5:  # not initialised: take the first valid acc(/mag) sample as orientation
        initialize_from_sample(state, acc, mag, mag_ok)
        return
    q, _ = propagate_gyro(load_quat(state), gyr, dt, max_dt)  # step 1
    if acc_ok:
        ok, q_am = acc_mag_quaternion(q, acc, mag, mag_ok)  # step 2
        if ok:
            b = 1.0 - alpha  # step 3
            q = normalize_scalar((b * q[0] + alpha * q_am[0], b * q[1] + alpha * q_am[1],
                                  b * q[2] + alpha * q_am[2], b * q[3] + alpha * q_am[3]))
            diag[0] = alpha
            diag[1] = 1.0 if mag_ok else 0.0
    store_quat(state, q)


class ComplementaryFilter(OrientationFilter):
    """Fixed-gain quaternion CF: ``ComplementaryFilter(fs, alpha=0.006, use_mag=True)``."""

    name = "cf"
    Settings = CFSettings
    Coefficients = CFCoefficients
    diagnostic_names = ("alpha", "mag_used")
    step = cf_step

    def _coefficients(self) -> dict:
        return {"alpha": self.settings.alpha}
