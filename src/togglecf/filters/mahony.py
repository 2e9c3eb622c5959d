"""Mahony's explicit nonlinear complementary filter with gyro-bias (integral) state.

R. Mahony, T. Hamel, J.-M. Pflimlin, "Nonlinear complementary filters on the special
orthogonal group", IEEE TAC 53(5), 2008, the explicit complementary filter with bias
correction (eq. 32 / 48 there; discretised as in Mahony's own MahonyAHRS.c and in ``ahrs``):

* eq. 32c/48a  ω_mes = Σ_i k_i v_i × v̂_i: measured directions â (and m̂) crossed with
  their predictions v̂_a = R̂ᵀ e_up, v̂_m = R̂ᵀ b (R̂ sensor -> earth)
* eq. 32b/48c  ḃ = −K_i ω_mes  (integral state: the gyro-bias estimate b̂, rad/s)
* eq. 32a/48b  q̇ = ½ q ⊗ [0, ω_y − b̂ + K_p ω_mes]
* first-order integration q ← normalize(q + q̇ Δt) (as MahonyAHRS.c and ``ahrs``).

Magnetic reference: h = R̂ m̂ in the earth frame, b = [0, √(h_x² + h_y²), h_z] in ENU (Mahony's
code writes [√(h_x² + h_y²), 0, h_z] in its NWU frame; the two are the same filter, rotated
about the vertical, so no frame conversion is needed here and the state stays ENU).

Differences from ``ahrs.filters.Mahony`` (only for invalid samples): we subtract b̂ from ω
also when the accelerometer is invalid (ahrs then uses the raw gyro), and a sample with
ω exactly zero is integrated normally (ahrs returns q unchanged and freezes b̂).
Bad samples (``filters.base``): invalid Δt -> skipped; non-finite or saturated gyro (an axis at
or beyond ``GYRO_FULL_SCALE``) -> ω_y = b̂ (only the correction acts); invalid acc -> no
correction, b̂ held; invalid mag in 9D -> gravity term only.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple

from numba import njit

from togglecf.core.quaternion import normalize_scalar, rotate_inverse_scalar, rotate_scalar
from togglecf.filters.base import (
    FilterSettings,
    OrientationFilter,
    dt_valid,
    gyro_valid,
    initialize_from_sample,
    load_quat,
    store_quat,
    vector_ok,
)

__all__ = ["MahonyFilter", "MahonySettings"]


@dataclass(frozen=True)
class MahonySettings(FilterSettings):
    """Attributes:
        Kp: proportional gain K_p [rad/s]. Default 0.7 (see Ki).
        Ki: integral gain K_i [rad/s²]. Default 0.0015. (Kp, Ki) is the TAGP over the 25
            BROAD trials in shared/ (9D, 285.7 Hz) of the grid Kp 0.1..1.6 × Ki 0..0.016
            (70 points), refined on Kp 0.6..0.9 × Ki 0.001..0.003. BROAD quotes K_p = 0.74,
            K_i = 0.0012 (close to it here). Heading is Mahony's weak point: with unit vectors, a heading error
            δψ gives ‖m̂ × v̂_m‖ ≈ cos²(dip)·δψ ≈ 0.15 δψ at BROAD's 67° dip, so the heading
            loop is ~6.5× slower than the tilt loop for the same K_p.
    """

    Kp: float = 0.7
    Ki: float = 0.0015

    def __post_init__(self):
        super().__post_init__()
        if not (self.Kp >= 0.0 and self.Ki >= 0.0):
            raise ValueError(f"Kp and Ki must be >= 0, got {self.Kp}, {self.Ki}")


class MahonyCoefficients(NamedTuple):
    """``params`` of ``mahony_step``: the common ``use_mag``, ``max_dt`` (see ``filters.base``), then
    the proportional gain ``Kp`` [rad/s] and the integral gain ``Ki`` [rad/s²] (``MahonySettings``)."""

    use_mag: float
    max_dt: float
    Kp: float
    Ki: float


@njit(cache=True)
def mahony_step(state, params, gyr, acc, mag, dt, diag):
    """One sample. state[5:8] is b̂. diag: [correction applied, mag used, b̂x, b̂y, b̂z, ‖ω_mes‖]."""
    use_mag, max_dt, kp, ki = params.use_mag > 0.5, params.max_dt, params.Kp, params.Ki
    acc_ok = vector_ok(acc)
    mag_ok = use_mag and vector_ok(mag)
    diag[0] = 0.0
    diag[1] = 0.0
    diag[5] = 0.0
    if state[4] < 0.5:
        initialize_from_sample(state, acc, mag, mag_ok)
        diag[2], diag[3], diag[4] = state[5], state[6], state[7]
        return
    if not dt_valid(dt, max_dt):
        diag[2], diag[3], diag[4] = state[5], state[6], state[7]
        return
    q = load_quat(state)
    gx, gy, gz = gyr[0], gyr[1], gyr[2]
    if not gyro_valid(gyr):  # non-finite or saturated: no gyro propagation (filters.base)
        gx, gy, gz = state[5], state[6], state[7]  # ω_y − b̂ = 0
    ex, ey, ez = 0.0, 0.0, 0.0
    if acc_ok:
        na = math.sqrt(acc[0] * acc[0] + acc[1] * acc[1] + acc[2] * acc[2])
        ax, ay, az = acc[0] / na, acc[1] / na, acc[2] / na
        vx, vy, vz = rotate_inverse_scalar(q, (0.0, 0.0, 1.0))  # v̂_a = R̂ᵀ e_up
        ex, ey, ez = ay * vz - az * vy, az * vx - ax * vz, ax * vy - ay * vx  # eq. 48a: â × v̂_a
        if mag_ok:
            nm = math.sqrt(mag[0] * mag[0] + mag[1] * mag[1] + mag[2] * mag[2])
            mx, my, mz = mag[0] / nm, mag[1] / nm, mag[2] / nm
            hx, hy, hz = rotate_scalar(q, (mx, my, mz))  # h = R̂ m̂
            wx, wy, wz = rotate_inverse_scalar(q, (0.0, math.sqrt(hx * hx + hy * hy), hz))  # v̂_m = R̂ᵀ b
            nw = math.sqrt(wx * wx + wy * wy + wz * wz)
            if nw > 0.0:
                wx, wy, wz = wx / nw, wy / nw, wz / nw
                ex += my * wz - mz * wy  # eq. 48a: + m̂ × v̂_m
                ey += mz * wx - mx * wz
                ez += mx * wy - my * wx
                diag[1] = 1.0
        # eq. 48c: ḃ = −K_i ω_mes (Euler step)
        state[5] -= ki * ex * dt
        state[6] -= ki * ey * dt
        state[7] -= ki * ez * dt
        diag[0] = 1.0
        diag[5] = math.sqrt(ex * ex + ey * ey + ez * ez)
    # eq. 48b: Ω = ω_y − b̂ + K_p ω_mes;  q̇ = ½ q ⊗ [0, Ω]
    ox = gx - state[5] + kp * ex
    oy = gy - state[6] + kp * ey
    oz = gz - state[7] + kp * ez
    h = 0.5 * dt
    q0, q1, q2, q3 = q
    store_quat(state, normalize_scalar((q0 + h * (-q1 * ox - q2 * oy - q3 * oz),
                                        q1 + h * (q0 * ox + q2 * oz - q3 * oy),
                                        q2 + h * (q0 * oy - q1 * oz + q3 * ox),
                                        q3 + h * (q0 * oz + q1 * oy - q2 * ox))))
    diag[2], diag[3], diag[4] = state[5], state[6], state[7]


class MahonyFilter(OrientationFilter):
    """Mahony's filter: ``MahonyFilter(fs, Kp=0.7, Ki=0.0015, use_mag=True)``."""

    name = "mahony"
    Settings = MahonySettings
    Coefficients = MahonyCoefficients
    state_names = ("bias_x", "bias_y", "bias_z")
    diagnostic_names = ("corrected", "mag_used", "bias_x", "bias_y", "bias_z", "omega_mes_norm")
    step = mahony_step

    def _coefficients(self) -> dict:
        return {"Kp": self.settings.Kp, "Ki": self.settings.Ki}
