"""Fixed-gain quaternion complementary filter.

Per sample (``Ts`` or the given Δt):

1. gyro propagation           q_g  = q ⊗ exp(ω Δt / 2)
2. acc/mag orientation        q_am = from_acc_mag(a, m)      (6D: a + predicted north)
3. complementary blend (LERP) q    = normalize((1 − α) q_g + α q_am),  q_am on q_g's hemisphere

α is the weight of the acc/mag measurement per sample, derived from the correction's time
constant ``CFSettings.tau`` [s] and the nominal sampling time: α = 1 − exp(−Ts/τ)
(``filters.timeconst``; the nominal ``Ts``, not each sample's Δt, as VQF does). So the same τ
corrects a tilt error with the same time constant in seconds at any sampling rate.
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
from togglecf.filters.timeconst import gain

__all__ = ["CFSettings", "ComplementaryFilter"]


@dataclass(frozen=True)
class CFSettings(FilterSettings):
    """Attributes:
        tau: time constant [s] of the acc/mag correction (per-sample weight α = 1 − exp(−Ts/τ);
            0: the acc/mag orientation alone, < 0: gyro only). Default 12.5 s: the
            per-sample α = 0.00028 at BROAD's 285.714 Hz (τ = −Ts/ln(1 − α) = 12.498 s),
            the TAGP over the 25 BROAD trials in shared/ (9D; coarse grid α 0.00002..0.05, then
            0.0002:0.0004:0.00002; its errors: ``docs/results``). Long, because this IMU's gyro
            biases (0.2-0.5 °/s) and up to ~2 m/s² of linear acceleration pull in opposite
            directions.
    """

    tau: float = 12.5


class CFCoefficients(NamedTuple):
    """``params`` of ``cf_step``: the common ``use_mag``, ``max_dt`` (see ``filters.base``), then
    ``alpha``, the weight of the acc/mag orientation per sample (from ``CFSettings.tau`` and ``Ts``)."""

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
    """Fixed-gain quaternion CF: ``ComplementaryFilter(fs, tau=12.5, use_mag=True)`` (τ in s)."""

    name = "cf"
    Settings = CFSettings
    Coefficients = CFCoefficients
    diagnostic_names = ("alpha", "mag_used")
    step = cf_step

    def _coefficients(self) -> dict:
        return {"alpha": gain(self.settings.tau, self.Ts)}
