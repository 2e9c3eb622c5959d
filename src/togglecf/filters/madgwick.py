"""Madgwick's gradient-descent orientation filter, IMU (6D) and MARG (9D) forms.

Equations of S. Madgwick, "An efficient orientation filter for inertial and inertial/magnetic
sensor arrays", report, University of Bristol, 2010 (equation numbers as cited by the
``ahrs`` package, which follows the report). Per sample, with the previous estimate q:

* eq. 12   q̇_ω = ½ q ⊗ [0, ω]
* eq. 25/26 (IMU) or 31/32 (MARG): objective f(q, â, m̂) and its Jacobian J, with the earth
  references d = [0, 0, 1] (gravity, z up) and, for MARG, b = [0, b_x, 0, b_z] from
  eq. 45 h = q ⊗ [0, m̂] ⊗ q*, eq. 46 b_x = √(h_x² + h_y²), b_z = h_z
* eq. 34   ∇f = Jᵀ f,  eq. 33  q̇ = q̇_ω − β ∇f / ‖∇f‖
* eq. 13   q ← normalize(q + q̇ Δt)      (first-order integration, as in the report)

Frames: the report's earth frame has x along magnetic north and z up (NWU). Our state
``state[0:4]`` stays sensor -> ENU as the framework requires; the kernel converts at its
boundary: ``q_nwu = ENU_FROM_NWU* ⊗ q_enu`` on entry, the report's equations run on
``q_nwu`` unchanged, and ``q_enu = ENU_FROM_NWU ⊗ q_nwu`` is stored on exit (a fixed +90°
rotation about the vertical). The sensor-frame inputs need no conversion.

The widely copied MadgwickAHRS.c computes ``_2bx = √(h_x² + h_y²)``, i.e. a reference b half
as long as eq. 46's (https://github.com/dlaidig/broad/issues/1); BROAD's published Madgwick results
come from that code. ``c_code_mag_step=True`` reproduces it for comparison; the default
is the report.

Bad samples (``filters.base``): invalid Δt -> the sample is skipped (nothing can be
integrated); non-finite or saturated gyro (an axis at or beyond ``GYRO_FULL_SCALE``) -> ω = 0
(the correction still runs); invalid acc -> no correction; invalid mag in 9D -> the IMU
equations for that sample.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple

from numba import njit

from togglecf.core.quaternion import ENU_FROM_NWU, multiply_scalar, normalize_scalar, rotate_scalar
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

__all__ = ["MadgwickFilter", "MadgwickSettings"]

_C = (float(ENU_FROM_NWU[0]), float(ENU_FROM_NWU[1]), float(ENU_FROM_NWU[2]), float(ENU_FROM_NWU[3]))
_CW, _CZ = _C[0], _C[3]


@dataclass(frozen=True)
class MadgwickSettings(FilterSettings):
    """Attributes:
        beta: gradient-descent gain β [rad/s]. Default 0.08, the TAGP of the grid
            0.01..0.30 (step 0.01) over the 25 BROAD trials in shared/ (9D, report equations,
            285.7 Hz). BROAD's published TAGP, β = 0.12, was found with the C code's magnetometer
            step (``c_code_mag_step``).
        c_code_mag_step: use MadgwickAHRS.c's half-length magnetic reference (see module
            docstring). Default False (the report's eq. 46). With it the TAGP of the grid
            0.02..0.20 (step 0.02) is β = 0.10, next to BROAD's 0.12.
    """

    beta: float = 0.08
    c_code_mag_step: bool = False

    def __post_init__(self):
        super().__post_init__()
        if not self.beta >= 0.0:
            raise ValueError(f"beta must be >= 0, got {self.beta}")


class MadgwickCoefficients(NamedTuple):
    """``params`` of ``madgwick_step``: the common ``use_mag``, ``max_dt`` (see ``filters.base``), then

    Attributes:
        beta: gradient-descent gain β [rad/s] (``MadgwickSettings.beta``).
        mag_ref_scale: factor on the magnetic reference b of eq. 46: 1.0 (the report) or 0.5
            (MadgwickAHRS.c, ``c_code_mag_step=True``).
    """

    use_mag: float
    max_dt: float
    beta: float
    mag_ref_scale: float


@njit(cache=True)
def madgwick_step(state, params, gyr, acc, mag, dt, diag):
    """One sample (see module docstring). diag: [β·Δt applied (0 without correction), mag used,
    ‖∇f‖ before normalisation]."""
    use_mag, max_dt, beta, bscale = params.use_mag > 0.5, params.max_dt, params.beta, params.mag_ref_scale
    acc_ok = vector_ok(acc)
    mag_ok = use_mag and vector_ok(mag)
    diag[0] = 0.0
    diag[1] = 0.0
    diag[2] = 0.0
    if state[4] < 0.5:
        initialize_from_sample(state, acc, mag, mag_ok)
        return
    if not dt_valid(dt, max_dt):
        return
    # boundary: ENU state -> NWU (the report's frame)
    qe = load_quat(state)
    q0, q1, q2, q3 = multiply_scalar((_CW, 0.0, 0.0, -_CZ), qe)
    gx, gy, gz = gyr[0], gyr[1], gyr[2]
    if not gyro_valid(gyr):  # non-finite or saturated: no gyro propagation (filters.base)
        gx, gy, gz = 0.0, 0.0, 0.0
    # eq. 12: q̇_ω = ½ q ⊗ [0, ω]
    d0 = 0.5 * (-q1 * gx - q2 * gy - q3 * gz)
    d1 = 0.5 * (q0 * gx + q2 * gz - q3 * gy)
    d2 = 0.5 * (q0 * gy - q1 * gz + q3 * gx)
    d3 = 0.5 * (q0 * gz + q1 * gy - q2 * gx)
    if acc_ok:
        na = math.sqrt(acc[0] * acc[0] + acc[1] * acc[1] + acc[2] * acc[2])
        ax, ay, az = acc[0] / na, acc[1] / na, acc[2] / na
        # eq. 25: f_g = q* ⊗ d ⊗ q − â with d = [0, 0, 0, 1]
        f1 = 2.0 * (q1 * q3 - q0 * q2) - ax
        f2 = 2.0 * (q0 * q1 + q2 * q3) - ay
        f3 = 2.0 * (0.5 - q1 * q1 - q2 * q2) - az
        # eq. 34 with eq. 26: ∇f = J_gᵀ f_g
        s0 = -2.0 * q2 * f1 + 2.0 * q1 * f2
        s1 = 2.0 * q3 * f1 + 2.0 * q0 * f2 - 4.0 * q1 * f3
        s2 = -2.0 * q0 * f1 + 2.0 * q3 * f2 - 4.0 * q2 * f3
        s3 = 2.0 * q1 * f1 + 2.0 * q2 * f2
        if mag_ok:
            nm = math.sqrt(mag[0] * mag[0] + mag[1] * mag[1] + mag[2] * mag[2])
            mx, my, mz = mag[0] / nm, mag[1] / nm, mag[2] / nm
            hx, hy, hz = rotate_scalar((q0, q1, q2, q3), (mx, my, mz))  # eq. 45: h = q ⊗ m̂ ⊗ q*
            bx = bscale * math.sqrt(hx * hx + hy * hy)  # eq. 46 (bscale 0.5: the C code)
            bz = bscale * hz
            # eq. 31 (rows 4-6): f_b = q* ⊗ b ⊗ q − m̂
            f4 = 2.0 * bx * (0.5 - q2 * q2 - q3 * q3) + 2.0 * bz * (q1 * q3 - q0 * q2) - mx
            f5 = 2.0 * bx * (q1 * q2 - q0 * q3) + 2.0 * bz * (q0 * q1 + q2 * q3) - my
            f6 = 2.0 * bx * (q0 * q2 + q1 * q3) + 2.0 * bz * (0.5 - q1 * q1 - q2 * q2) - mz
            # eq. 34 with eq. 32 (rows 4-6 of J_g,b)
            s0 += -2.0 * bz * q2 * f4 + (-2.0 * bx * q3 + 2.0 * bz * q1) * f5 + 2.0 * bx * q2 * f6
            s1 += 2.0 * bz * q3 * f4 + (2.0 * bx * q2 + 2.0 * bz * q0) * f5 + (2.0 * bx * q3 - 4.0 * bz * q1) * f6
            s2 += ((-4.0 * bx * q2 - 2.0 * bz * q0) * f4 + (2.0 * bx * q1 + 2.0 * bz * q3) * f5
                   + (2.0 * bx * q0 - 4.0 * bz * q2) * f6)
            s3 += (-4.0 * bx * q3 + 2.0 * bz * q1) * f4 + (-2.0 * bx * q0 + 2.0 * bz * q2) * f5 + 2.0 * bx * q1 * f6
            diag[1] = 1.0
        ns = math.sqrt(s0 * s0 + s1 * s1 + s2 * s2 + s3 * s3)
        diag[2] = ns
        if ns > 0.0:
            # eq. 33: q̇ = q̇_ω − β ∇f/‖∇f‖
            d0 -= beta * s0 / ns
            d1 -= beta * s1 / ns
            d2 -= beta * s2 / ns
            d3 -= beta * s3 / ns
            diag[0] = beta * dt
    # eq. 13: q ← normalize(q + q̇ Δt)
    qn = normalize_scalar((q0 + d0 * dt, q1 + d1 * dt, q2 + d2 * dt, q3 + d3 * dt))
    store_quat(state, multiply_scalar((_CW, 0.0, 0.0, _CZ), qn))  # boundary: NWU -> ENU


class MadgwickFilter(OrientationFilter):
    """Madgwick's filter: ``MadgwickFilter(fs, beta=0.08, use_mag=True)``."""

    name = "madgwick"
    Settings = MadgwickSettings
    Coefficients = MadgwickCoefficients
    diagnostic_names = ("beta_dt", "mag_used", "grad_norm")
    step = madgwick_step

    def _coefficients(self) -> dict:
        return {"beta": self.settings.beta, "mag_ref_scale": 0.5 if self.settings.c_code_mag_step else 1.0}
