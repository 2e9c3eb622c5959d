"""Error-state (indirect) Kalman filter in the style of MATLAB's ``imufilter``/``ahrsfilter``.

Error state (12): δθ orientation error (body frame, rad; q_true = q̂ ⊗ exp(δθ)), δb gyro-bias
error (rad/s), δa linear-acceleration error (sensor frame, m/s²), δd magnetic-disturbance
error (sensor frame, µT; 9D only, its rows/columns are unused in 6D). Per sample, with
κ = Δt (MATLAB: DecimationFactor/fs):

* predict: q⁻ = q⁺ ⊗ exp((ω − b̂) κ / 2); â⁻ = ν â⁺; d̂⁻ = σ d̂⁺
* P⁻ = Q_k (MATLAB's choice: the prior covariance *is* the process noise built from P⁺), with
  one addition: the orientation block is carried along the body rotation, Φ = R(Δq)ᵀ:
  Q_θθ = Φ P⁺_θθ Φᵀ + κ²(P⁺_bb + (β + η) I), Q_θb = Q_bθ = −κ(P⁺_bb + β I), Q_bb = P⁺_bb + β I,
  Q_aa = ν² P⁺_aa + ξ I, Q_dd = σ² P⁺_dd + γ I, other blocks 0
* gravity innovation: ĝ_s = R̂ᵀ [0, 0, g] (ENU, specific force at rest points up), model
  y_a = g_s + a_lin: z_a = y_a − (ĝ_s + â⁻), H_a = [ [ĝ_s]×, −κ[ĝ_s]×, I, 0 ],
  R_a = λ + ξ + κ²(β + η)
* magnetic innovation (9D): m̂_s = R̂ᵀ m_ref, m_ref = [0, M_h, M_v] (ENU), model y_m = m_s + d:
  z_m = y_m − (m̂_s + d̂⁻), H_m = [ [m̂_s]×, −κ[m̂_s]×, 0, I ], R_m = μ + γ + κ²(β + η) M²;
  skipped when ‖y_m‖² > 4 M_expected² (MATLAB's jamming test)
* K = P⁻Hᵀ(H P⁻ Hᵀ + R)⁻¹, x = K z, P⁺ = P⁻ − K H P⁻: done as sequential scalar updates, one
  innovation row at a time (exactly equivalent for a diagonal R; no matrix inverse, no
  allocation)
* correct: q⁺ = q⁻ ⊗ exp(δθ), b̂⁺ = b̂⁻ + δb, â⁺ = â⁻ + δa, d̂⁺ = d̂⁻ + δd; in 9D the reference
  m_ref (horizontal and vertical parts) slowly tracks R⁺ y_m (``mag_ref_rate``; MATLAB
  re-sets it from R⁺(y_m − d̂⁺) every sample, which was unstable on BROAD, see settings).

Derivation of H (ours, in the ENU/sensor->earth convention): with R = R̂(I + [δθ]×),
Rᵀ e = ê − δθ × ê = ê + [ê]× δθ; a bias error δb rotates the estimate by −κ δb over the step.
P (12×12, row-major) lives in the state vector, so get_state/set_state capture it.

Bad samples (``filters.base``): invalid Δt or gyro (non-finite, or saturated: an axis of the raw
reading at or beyond ``GYRO_FULL_SCALE``) -> no propagation (κ = 0 in Q); invalid acc -> no
gravity update; invalid mag -> no magnetic update.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
from numba import njit

from togglecf.core.quaternion import (
    from_rotvec_scalar,
    multiply_scalar,
    normalize_scalar,
    rotate_inverse_scalar,
    rotate_scalar,
)
from togglecf.filters.base import (
    FilterSettings,
    OrientationFilter,
    gyro_valid,
    initialize_from_sample,
    load_quat,
    propagate_gyro,
    store_quat,
    vector_ok,
)

__all__ = ["EKFFilter", "EKFSettings"]

NX = 12
_OFF_B, _OFF_A, _OFF_D, _OFF_M, _OFF_P = 5, 8, 11, 14, 16
#: MATLAB's initial error covariance diagonal (orientation, bias, lin. acc., mag. disturbance)
P0_DIAG = (6.092348396e-6,) * 3 + (7.6154354947e-5,) * 3 + (9.62361e-3,) * 3 + (0.6,) * 3


@dataclass(frozen=True)
class EKFSettings(FilterSettings):
    """Noise parameters in MATLAB's units, here for rad/s, m/s² and µT. Defaults: the TAGP over
    the 25 BROAD trials in shared/ (9D, 285.7 Hz) of successive grids (gyro_noise 1e-6..0.1,
    linacc_noise 0.001..30, mag_disturbance_noise 0.5..500, mag_noise 0.1/1, linacc_decay
    0.3..0.9, gyro_drift_noise 3e-13..1e-8, mag_ref_rate 0..1; ~190 points). MATLAB's noise
    defaults (in brackets) trust the accelerometer and magnetometer far too much for BROAD's
    motions (several times the error there).

    Attributes:
        gyro_noise: η, gyroscope noise variance [(rad/s)²]. Default 0.02 (9.1385e-5).
        gyro_drift_noise: β, bias random-walk variance per step [(rad/s)²]. Default 3.0462e-13
            (same; 1e-11 scores the same, 1e-8 worse).
        acc_noise: λ, accelerometer noise variance [(m/s²)²]. Default 0.00019247 (same).
        linacc_noise: ξ, linear-acceleration variance [(m/s²)²]. Default 3.0 (0.0096236).
        linacc_decay: ν, per-step decay of the linear-acceleration estimate. Default 0.5 (same).
        mag_noise: μ, magnetometer noise variance [µT²]. Default 0.1 (same; 1.0 scores the same).
        mag_disturbance_noise: γ, magnetic-disturbance variance [µT²]. Default 50.0 (0.5).
        mag_disturbance_decay: σ, per-step decay of the disturbance estimate. Default 0.5 (same).
        expected_mag_strength: M_expected [µT], for the jamming test. Default 50.0 (same).
        gravity: g [m/s²]. Default 9.81.
        mag_ref_rate: per-sample low-pass gain with which the reference field m_ref = [0, M_h,
            M_v] tracks the measured field in the earth frame, R⁺ y_m (0: keep the first
            sample's). Default 0.005 (~0.7 s at 285.7 Hz; better than 0 or 1 there). MATLAB re-sets
            the reference from R⁺(y_m − d̂⁺) every sample; here that fed back into d̂ and shrank
            M_h towards 0 on BROAD, leaving the heading unobservable, hence this version.
    """

    gyro_noise: float = 0.02
    gyro_drift_noise: float = 3.0462e-13
    acc_noise: float = 0.00019247
    linacc_noise: float = 3.0
    linacc_decay: float = 0.5
    mag_noise: float = 0.1
    mag_disturbance_noise: float = 50.0
    mag_disturbance_decay: float = 0.5
    expected_mag_strength: float = 50.0
    gravity: float = 9.81
    mag_ref_rate: float = 0.005

    def __post_init__(self):
        super().__post_init__()
        if not 0.0 <= self.mag_ref_rate <= 1.0:
            raise ValueError(f"mag_ref_rate must be in [0, 1], got {self.mag_ref_rate}")
        for k in ("gyro_noise", "gyro_drift_noise", "acc_noise", "linacc_noise", "mag_noise", "mag_disturbance_noise"):
            if not getattr(self, k) >= 0.0:
                raise ValueError(f"{k} must be >= 0, got {getattr(self, k)}")
        for k in ("linacc_decay", "mag_disturbance_decay"):
            if not 0.0 <= getattr(self, k) <= 1.0:
                raise ValueError(f"{k} must be in [0, 1], got {getattr(self, k)}")
        if not (self.expected_mag_strength > 0 and self.gravity > 0):
            raise ValueError("expected_mag_strength and gravity must be > 0")


class EKFCoefficients(NamedTuple):
    """``params`` of ``ekf_step``: the common ``use_mag``, ``max_dt`` (see ``filters.base``), then
    the ``EKFSettings`` of the same names (η, β, λ, ξ, ν, μ, γ, σ, M_expected, g, the m_ref rate)."""

    use_mag: float
    max_dt: float
    gyro_noise: float
    gyro_drift_noise: float
    acc_noise: float
    linacc_noise: float
    linacc_decay: float
    mag_noise: float
    mag_disturbance_noise: float
    mag_disturbance_decay: float
    expected_mag_strength: float
    gravity: float
    mag_ref_rate: float


@njit(cache=True, inline="always")
def _scalar_update(P, x, ph, hs, kap, u, z, r, n):
    """One scalar Kalman update with the measurement row h = [hs, −κ hs, e_u] (hs: the row of
    the skew matrix acting on δθ, e_u the unit entry of δa or δd), innovation z, noise r.
    Updates P (flat 12×12, in place) and the error estimate x; ``ph`` is scratch (12). Only the
    first ``n`` error states take part (9 in 6D: the δd block is then decoupled and unused)."""
    for i in range(n):
        row = i * NX
        ph[i] = (P[row] * hs[0] + P[row + 1] * hs[1] + P[row + 2] * hs[2]
                 - kap * (P[row + 3] * hs[0] + P[row + 4] * hs[1] + P[row + 5] * hs[2]) + P[row + u])  # P hᵀ
    s = r + hs[0] * ph[0] + hs[1] * ph[1] + hs[2] * ph[2] - kap * (hs[0] * ph[3] + hs[1] * ph[4] + hs[2] * ph[5]) + ph[u]
    zr = z - (hs[0] * x[0] + hs[1] * x[1] + hs[2] * x[2] - kap * (hs[0] * x[3] + hs[1] * x[4] + hs[2] * x[5]) + x[u])
    if not (s > 0.0):
        return
    inv_s = 1.0 / s
    for i in range(n):
        x[i] += ph[i] * zr * inv_s  # x += K (z − h x), K = P hᵀ / s (earlier rows explained part of z)
    for i in range(n):
        row = i * NX
        pi = ph[i]
        for j in range(i, n):  # P −= K h P = P hᵀ (P hᵀ)ᵀ / s; upper triangle, mirrored: exactly symmetric
            v = P[row + j] - (pi * ph[j]) * inv_s
            P[row + j] = v
            P[j * NX + i] = v


@njit(cache=True, inline="always")
def _initialize(state, P, acc, mag, mag_ok):
    """The first usable sample: orientation from it, b̂ = â = d̂ = 0, P = P₀, the reference field."""
    if initialize_from_sample(state, acc, mag, mag_ok):
        for i in range(_OFF_B, _OFF_P + NX * NX):
            state[i] = 0.0
        for i in range(NX):
            P[i * NX + i] = P0_DIAG[i]
        if mag_ok:  # reference field from the first sample
            mx, my, mz = rotate_scalar(load_quat(state), (mag[0], mag[1], mag[2]))
            state[_OFF_M] = math.sqrt(mx * mx + my * my)
            state[_OFF_M + 1] = mz


@njit(cache=True, inline="always")
def _rotate_covariance(P, q_prev, q, scratch):
    """Body-frame error: δθ_k = Φ δθ_{k-1} − κ δb with Φ = R(Δq)ᵀ, Δq = q⁻_{k-1}* ⊗ q⁻_k: P_θθ ← Φ P_θθ Φᵀ.
    MATLAB's Q_k omits Φ; without it P_θθ keeps the large heading variance on the wrong body axis
    once the sensor turns, and accelerometer updates leak into the heading (BROAD 15: 45°)."""
    w, x1, y1, z1 = multiply_scalar((q_prev[0], -q_prev[1], -q_prev[2], -q_prev[3]), q)
    phi = scratch[2 * NX:2 * NX + 9]  # Φ = R(Δq)ᵀ, row-major
    phi[0], phi[1], phi[2] = 1 - 2 * (y1 * y1 + z1 * z1), 2 * (x1 * y1 + w * z1), 2 * (x1 * z1 - w * y1)
    phi[3], phi[4], phi[5] = 2 * (x1 * y1 - w * z1), 1 - 2 * (x1 * x1 + z1 * z1), 2 * (y1 * z1 + w * x1)
    phi[6], phi[7], phi[8] = 2 * (x1 * z1 + w * y1), 2 * (y1 * z1 - w * x1), 1 - 2 * (x1 * x1 + y1 * y1)
    tmp = scratch[2 * NX + 9:]
    for i in range(3):
        for j in range(3):  # tmp = P_θθ Φᵀ
            tmp[i * 3 + j] = P[i * NX] * phi[j * 3] + P[i * NX + 1] * phi[j * 3 + 1] + P[i * NX + 2] * phi[j * 3 + 2]
    for i in range(3):
        for j in range(3):  # P_θθ = Φ tmp
            P[i * NX + j] = phi[i * 3] * tmp[j] + phi[i * 3 + 1] * tmp[3 + j] + phi[i * 3 + 2] * tmp[6 + j]
    for i in range(3):
        for j in range(i + 1, 3):  # exact symmetry
            v = 0.5 * (P[i * NX + j] + P[j * NX + i])
            P[i * NX + j] = v
            P[j * NX + i] = v


@njit(cache=True, inline="always")
def _process_noise(P, params, kap, nx):
    """P⁻ = Q_k from P⁺ (blocks of 3; θ = 0, b = 3, a = 6, d = 9)."""
    eta, beta = params.gyro_noise, params.gyro_drift_noise
    xi, nu = params.linacc_noise, params.linacc_decay
    gam, sig = params.mag_disturbance_noise, params.mag_disturbance_decay
    for i in range(3):
        for j in range(3):
            pbb = P[(3 + i) * NX + 3 + j]
            e = 1.0 if i == j else 0.0
            P[i * NX + j] = P[i * NX + j] + kap * kap * (pbb + (beta + eta) * e)
            P[i * NX + 3 + j] = -kap * (pbb + beta * e)
            P[(3 + i) * NX + j] = -kap * (P[(3 + j) * NX + 3 + i] + beta * e)
    for i in range(3):
        for j in range(3):
            e = 1.0 if i == j else 0.0
            P[(3 + i) * NX + 3 + j] += beta * e
            P[(6 + i) * NX + 6 + j] = nu * nu * P[(6 + i) * NX + 6 + j] + xi * e
            P[(9 + i) * NX + 9 + j] = sig * sig * P[(9 + i) * NX + 9 + j] + gam * e
    for i in range(6):  # cross blocks of (θ, b) with a and d, and of a with d, are zero in Q_k
        for j in range(6, nx):
            P[i * NX + j] = 0.0
            P[j * NX + i] = 0.0
    for i in range(6, 9):
        for j in range(9, nx):
            P[i * NX + j] = 0.0
            P[j * NX + i] = 0.0


@njit(cache=True, inline="always")
def _acc_update(state, P, x, ph, params, q, acc, kap):
    """The accelerometer's three scalar updates: a = ĝ_s + â, ĝ_s = R̂ᵀ [0, 0, g]."""
    eta, beta, lam, xi = params.gyro_noise, params.gyro_drift_noise, params.acc_noise, params.linacc_noise
    gx, gy, gz = rotate_inverse_scalar(q, (0.0, 0.0, params.gravity))  # ĝ_s = R̂ᵀ [0, 0, g]
    ra = lam + xi + kap * kap * (beta + eta)
    # rows of [ĝ_s]× : (0, −gz, gy), (gz, 0, −gx), (−gy, gx, 0)
    sk = ((0.0, -gz, gy), (gz, 0.0, -gx), (-gy, gx, 0.0))
    pred = (gx + state[_OFF_A], gy + state[_OFF_A + 1], gz + state[_OFF_A + 2])
    for r in range(3):
        _scalar_update(P, x, ph, sk[r], kap, 6 + r, acc[r] - pred[r], ra, 9)  # δd is decoupled here


@njit(cache=True, inline="always")
def _mag_update(state, P, x, ph, params, q, mag, kap, nx) -> bool:
    """The magnetometer's three scalar updates (m = R̂ᵀ m_ref + d̂), unless the field is jammed (over
    twice the expected strength): returns False then."""
    eta, beta, mu, gam = params.gyro_noise, params.gyro_drift_noise, params.mag_noise, params.mag_disturbance_noise
    m_exp = params.expected_mag_strength
    mm2 = mag[0] * mag[0] + mag[1] * mag[1] + mag[2] * mag[2]
    if mm2 > 4.0 * m_exp * m_exp:
        return False
    mh, mv = state[_OFF_M], state[_OFF_M + 1]
    mx, my, mz = rotate_inverse_scalar(q, (0.0, mh, mv))  # m̂_s = R̂ᵀ m_ref
    rm = mu + gam + kap * kap * (beta + eta) * (mh * mh + mv * mv)
    sk = ((0.0, -mz, my), (mz, 0.0, -mx), (-my, mx, 0.0))
    pred = (mx + state[_OFF_D], my + state[_OFF_D + 1], mz + state[_OFF_D + 2])
    for r in range(3):
        _scalar_update(P, x, ph, sk[r], kap, 9 + r, mag[r] - pred[r], rm, nx)
    return True


@njit(cache=True, inline="always")
def _correct(state, x, q, mag, mag_used, mref_rate):
    """q⁺ = q⁻ ⊗ exp(δθ), b̂, â, d̂ += their errors; the reference field tracked slowly (low-pass)."""
    q = normalize_scalar(multiply_scalar(q, from_rotvec_scalar(x[0], x[1], x[2])))  # q⁺ = q⁻ ⊗ exp(δθ)
    for i in range(3):
        state[_OFF_B + i] += x[3 + i]
        state[_OFF_A + i] += x[6 + i]
        state[_OFF_D + i] += x[9 + i]
    if mag_used and mref_rate > 0.0:  # track the reference field slowly (low-pass)
        mx, my, mz = rotate_scalar(q, (mag[0], mag[1], mag[2]))
        state[_OFF_M] += mref_rate * (math.sqrt(mx * mx + my * my) - state[_OFF_M])
        state[_OFF_M + 1] += mref_rate * (mz - state[_OFF_M + 1])
    return q


@njit(cache=True)
def ekf_step(state, params, gyr, acc, mag, dt, diag):
    """One sample. diag: [acc used, mag used, b̂x, b̂y, b̂z, ‖â‖, orientation std (deg), mag jammed]."""
    use_mag = params.use_mag > 0.5
    nx = NX if use_mag else 9  # 6D: the magnetic-disturbance block takes no part
    acc_ok = vector_ok(acc)
    mag_ok = use_mag and vector_ok(mag)
    for i in range(8):
        diag[i] = 0.0
    P = state[_OFF_P:_OFF_P + NX * NX]
    if state[4] < 0.5:
        _initialize(state, P, acc, mag, mag_ok)
        return
    # --- predict
    scratch = np.empty(2 * NX + 18)  # the one allocation per sample: x, P hᵀ, two 3×3 blocks
    for i in range(NX):
        scratch[i] = 0.0  # x
    bx, by, bz = state[_OFF_B], state[_OFF_B + 1], state[_OFF_B + 2]
    q_prev = load_quat(state)
    q, done = q_prev, False
    if gyro_valid(gyr):  # the saturation test is on the raw reading, not on ω − b̂ (filters.base)
        q, done = propagate_gyro(q_prev, (gyr[0] - bx, gyr[1] - by, gyr[2] - bz), dt, params.max_dt)
    kap = dt if done else 0.0
    if done:
        _rotate_covariance(P, q_prev, q, scratch)
    for i in range(3):
        state[_OFF_A + i] *= params.linacc_decay
        state[_OFF_D + i] *= params.mag_disturbance_decay
    _process_noise(P, params, kap, nx)
    # --- measurement updates (sequential scalar form)
    x = scratch[:NX]
    ph = scratch[NX:]
    if acc_ok:
        _acc_update(state, P, x, ph, params, q, acc, kap)
        diag[0] = 1.0
    if mag_ok:
        if _mag_update(state, P, x, ph, params, q, mag, kap, nx):
            diag[1] = 1.0
        else:
            diag[7] = 1.0
    # --- correct
    if diag[0] > 0.5 or diag[1] > 0.5:
        q = _correct(state, x, q, mag, diag[1] > 0.5, params.mag_ref_rate)
    store_quat(state, q)
    diag[2], diag[3], diag[4] = state[_OFF_B], state[_OFF_B + 1], state[_OFF_B + 2]
    diag[5] = math.sqrt(state[_OFF_A] ** 2 + state[_OFF_A + 1] ** 2 + state[_OFF_A + 2] ** 2)
    tr = P[0] + P[NX + 1] + P[2 * NX + 2]
    diag[6] = math.degrees(math.sqrt(max(tr, 0.0)))


class EKFFilter(OrientationFilter):
    """Error-state Kalman filter (MATLAB imufilter/ahrsfilter style): ``EKFFilter(fs, use_mag=True)``."""

    name = "ekf"
    Settings = EKFSettings
    Coefficients = EKFCoefficients
    state_names = (("bias_x", "bias_y", "bias_z", "linacc_x", "linacc_y", "linacc_z",
                     "magdist_x", "magdist_y", "magdist_z", "mag_ref_h", "mag_ref_v")
                    + tuple(f"P_{i}_{j}" for i in range(NX) for j in range(NX)))
    diagnostic_names = ("acc_used", "mag_used", "bias_x", "bias_y", "bias_z", "linacc_norm", "orient_std_deg",
                        "mag_jammed")
    step = ekf_step

    def _coefficients(self) -> dict:
        s = self.settings
        return {f: getattr(s, f) for f in EKFCoefficients._fields[2:]}
