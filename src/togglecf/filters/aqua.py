"""AQUA: algebraic quaternion complementary filter with adaptive gain and bias estimation.

R. Valenti, I. Dryanovski, J. Xiao, "Keeping a good attitude: a quaternion-based orientation
filter for IMUs and MARGs", Sensors 15(8):19302-19330, 2015 (equation numbers as cited by
``ahrs.filters.AQUA``, which follows the paper). Per sample:

1. steady-state gyro bias (as in the authors' imu_tools implementation): if |‖a‖ − g| < k_a
   and every |ω_i − ω_prev,i| < k_Δω and |ω_i − b_i| < k_ω, then b ← b + λ_b (ω − b)
2. prediction (eq. 39, 42; exact exponential instead of the paper's first-order step)
                                     q_ω = q ⊗ exp((ω − b) Δt / 2)
3. accelerometer correction (eq. 44-53): predicted gravity g_p = R(q_ω) â (earth frame);
   Δq_acc = [√((g_z+1)/2), g_y/√(2(g_z+1)), −g_x/√(2(g_z+1)), 0] rotates g_p onto up;
   scaled towards identity with the adaptive gain α (eq. 60-61, ``adaptive_gain``) by LERP
   when Δq_w > ε (eq. 50-51) else SLERP (eq. 52); q' = Δq̄_acc ⊗ q_ω (eq. 53)
4. magnetometer correction, 9D (eq. 54-59): l = R(q') m̂ (earth frame, eq. 54), Γ = l_x² + l_y²;
   Δq_mag rotates l's horizontal part onto north about the vertical only; scaled with the
   constant gain β̄ the same way; q = Δq̄_mag ⊗ q'.

Gains: the paper's ᾱ, β̄ and λ_b are per-sample weights; here each is set as a time constant
[s] (``tau_acc``, ``tau_mag``, ``bias_tau``) and converted once from the nominal ``Ts`` as
k = 1 − exp(−Ts/τ) (``filters.timeconst``), so the same settings mean the same at any rate.

Conventions: the paper's quaternion ^L_G q is the conjugate of ours (sensor -> earth) and its
global frame is x north (NWU). Therefore Δq here is the conjugate of the paper's and is
applied on the left; Δq_mag is the paper's eq. 58 with (l_x, l_y)_NWU = (l_y, −l_x)_ENU:
Δq_mag = [√(Γ + l_y√Γ)/√(2Γ), 0, 0, l_x/√(2(Γ + l_y√Γ))] (a rotation about the vertical is
the same quaternion in NWU and ENU).

Bad samples (``filters.base``): invalid Δt or gyro (non-finite, or saturated: an axis of the raw
reading at or beyond ``GYRO_FULL_SCALE``) -> no prediction and no bias update, and an invalid
gyro sample is not kept as the previous ω; invalid acc -> no correction (nor the magnetometer
step); invalid mag -> no heading correction.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple

from numba import njit

from togglecf.core.quaternion import multiply_scalar, normalize_scalar, rotate_scalar
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
from togglecf.filters.timeconst import gain

__all__ = ["AquaFilter", "AquaSettings", "adaptive_gain", "scale_delta_quat"]


@dataclass(frozen=True)
class AquaSettings(FilterSettings):
    """Attributes (defaults: the TAGP over the 25 BROAD trials in shared/, 9D, 285.7 Hz, found on
    per-sample ᾱ × β̄ grids (0.00005..0.02 × 0.00002..0.01, coarse to fine, bias on/off)
    and then on the bias thresholds; the bias estimation roughly halves the error there. The time constants
    below are those per-sample gains α at BROAD's 285.714 Hz, τ = −Ts/ln(1 − α), rounded):

        tau_acc: time constant [s] of the accelerometer correction; the static gain
            ᾱ = 1 − exp(−Ts/τ) (0: ᾱ = 1, < 0: off). Default 11.66 s (ᾱ = 0.0003 at 285.714 Hz).
        tau_mag: time constant [s] of the magnetometer (heading) correction, β̄ likewise.
            Default 70.0 s (β̄ = 0.00005 at 285.714 Hz).
        adaptive: scale ᾱ with ``adaptive_gain`` (True, default) or use it as is.
        err_low, err_high: magnitude-error thresholds t1 < t2 of the adaptive gain
            (e_m = |‖a‖ − g|/g): full gain up to t1 (0.1), linear fall to zero at t2 (0.2).
        lerp_threshold: ε; Δq_w > ε uses LERP, else SLERP. Default 0.9 (the paper's).
        gravity: g [m/s²]. Default 9.81.
        bias_tau: time constant [s] of the steady-state bias low-pass, λ_b = 1 − exp(−Ts/τ)
            (< 0: off). Default 1.748 s (λ_b = 0.002 at 285.714 Hz; imu_tools' 0.01 at its rate).
        acc_threshold: k_a [m/s²], |‖a‖ − g| below it counts as steady. Default 0.1.
        delta_gyro_threshold: k_Δω [rad/s], per-axis change of ω between samples. Default 0.03
            (imu_tools: 0.01; BROAD's gyro noise at 285.7 Hz often exceeds 0.01 at rest). A
            threshold on the sample-to-sample change, dominated by the gyro's noise, so it is
            kept per sample (not converted to rad/s²).
        gyro_threshold: k_ω [rad/s], per-axis |ω − b|. Default 0.05 (imu_tools: 0.2, which
            lets slow rotations, e.g. of a gimbal, count as "steady" and leak into b).
        estimate_bias: enable the bias update (default True).
    """

    tau_acc: float = 11.66
    tau_mag: float = 70.0
    adaptive: bool = True
    err_low: float = 0.1
    err_high: float = 0.2
    lerp_threshold: float = 0.9
    gravity: float = 9.81
    bias_tau: float = 1.748
    acc_threshold: float = 0.1
    delta_gyro_threshold: float = 0.03
    gyro_threshold: float = 0.05
    estimate_bias: bool = True

    def __post_init__(self):
        super().__post_init__()
        if not 0.0 <= self.err_low < self.err_high:
            raise ValueError(f"need 0 <= err_low < err_high, got {self.err_low}, {self.err_high}")
        if not (self.gravity > 0 and self.acc_threshold >= 0 and self.delta_gyro_threshold >= 0
                and self.gyro_threshold >= 0 and -1.0 <= self.lerp_threshold <= 1.0):
            raise ValueError("gravity must be > 0, thresholds >= 0, lerp_threshold in [-1, 1]")


class AquaCoefficients(NamedTuple):
    """``params`` of ``aqua_step``: the common ``use_mag``, ``max_dt`` (see ``filters.base``), then
    the per-sample gains ``gain_acc`` (ᾱ), ``gain_mag`` (β̄) and ``bias_alpha`` (λ_b) from the
    settings' ``tau_acc``, ``tau_mag``, ``bias_tau`` and ``Ts``, and the other ``AquaSettings`` of
    the same names (the two switches ``adaptive`` and ``estimate_bias`` as 1.0/0.0)."""

    use_mag: float
    max_dt: float
    gain_acc: float
    gain_mag: float
    adaptive: float
    err_low: float
    err_high: float
    lerp_threshold: float
    gravity: float
    bias_alpha: float
    acc_threshold: float
    delta_gyro_threshold: float
    gyro_threshold: float
    estimate_bias: float


@njit(cache=True, inline="always")
def adaptive_gain(alpha_bar, acc_norm, gravity, t1, t2):
    """Eq. 60-61: α = ᾱ·f(e_m), e_m = |‖a‖ − g|/g; f = 1 for e_m ≤ t1, (t2 − e_m)/(t2 − t1)
    for t1 < e_m < t2, 0 for e_m ≥ t2 (and for a non-finite norm)."""
    e = abs(acc_norm - gravity) / gravity
    if e <= t1:
        return alpha_bar
    if e < t2:
        return alpha_bar * (t2 - e) / (t2 - t1)
    return 0.0


@njit(cache=True, inline="always")
def scale_delta_quat(dq, gain, eps):
    """Eq. 50-52: interpolate from identity towards unit ``dq`` (w >= 0) by ``gain``: LERP
    (normalised) when dq_w > ε, else SLERP. Returns ``(Δq̄, used_slerp)``."""
    if dq[0] > eps:
        b = 1.0 - gain  # eq. 50: (1 − α) q_I + α Δq, eq. 51: normalise
        return normalize_scalar((b + gain * dq[0], gain * dq[1], gain * dq[2], gain * dq[3])), False
    omega = math.acos(min(1.0, max(-1.0, dq[0])))  # eq. 52: cos Ω = Δq_w
    s = math.sin(omega)
    if s < 1e-12:
        return (1.0, 0.0, 0.0, 0.0), True
    wi = math.sin((1.0 - gain) * omega) / s
    wd = math.sin(gain * omega) / s
    return normalize_scalar((wi + wd * dq[0], wd * dq[1], wd * dq[2], wd * dq[3])), True


@njit(cache=True)
def aqua_step(state, params, gyr, acc, mag, dt, diag):
    """One sample. state[5:8] bias b [rad/s], state[8:11] previous ω, state[11] 1.0 when it is
    valid. diag: [α used, steady, b_x, b_y, b_z, mag used, SLERP used]."""
    use_mag, max_dt = params.use_mag > 0.5, params.max_dt
    gain_acc, gain_mag, adaptive = params.gain_acc, params.gain_mag, params.adaptive > 0.5
    t1, t2, eps = params.err_low, params.err_high, params.lerp_threshold
    grav, lam, est_bias = params.gravity, params.bias_alpha, params.estimate_bias > 0.5
    k_a, k_dw, k_w = params.acc_threshold, params.delta_gyro_threshold, params.gyro_threshold
    acc_ok = vector_ok(acc)
    mag_ok = use_mag and vector_ok(mag)
    for i in range(7):
        diag[i] = 0.0
    gyr_ok = gyro_valid(gyr)  # finite and not saturated (judged on the raw reading)
    if state[4] < 0.5:
        initialize_from_sample(state, acc, mag, mag_ok)
    else:
        na = math.sqrt(acc[0] * acc[0] + acc[1] * acc[1] + acc[2] * acc[2]) if acc_ok else math.nan
        dt_ok = math.isfinite(dt) and dt > 0.0 and dt <= max_dt
        # 1. steady-state bias update
        if est_bias and gyr_ok and dt_ok and acc_ok and state[11] > 0.5:
            steady = abs(na - grav) < k_a
            for i in range(3):
                if not (abs(gyr[i] - state[8 + i]) < k_dw and abs(gyr[i] - state[5 + i]) < k_w):
                    steady = False
            if steady:
                for i in range(3):
                    state[5 + i] += lam * (gyr[i] - state[5 + i])
                diag[1] = 1.0
        # 2. prediction with the bias-corrected rate
        q = load_quat(state)
        if gyr_ok:
            q, _ = propagate_gyro(q, (gyr[0] - state[5], gyr[1] - state[6], gyr[2] - state[7]), dt, max_dt)
        if acc_ok:
            # 3. accelerometer delta quaternion from the predicted gravity g_p = R(q_ω) â (eq. 44)
            gx, gy, gz = rotate_scalar(q, (acc[0] / na, acc[1] / na, acc[2] / na))
            if gz > -1.0 + 1e-9:
                r = math.sqrt(2.0 * (gz + 1.0))
                dq = (math.sqrt(0.5 * (gz + 1.0)), gy / r, -gx / r, 0.0)  # eq. 47 (conjugated, see above)
            else:  # g_p points straight down: 180° about x
                dq = (0.0, 1.0, 0.0, 0.0)
            alpha = adaptive_gain(gain_acc, na, grav, t1, t2) if adaptive else gain_acc  # eq. 60
            dqs, slerp = scale_delta_quat(dq, alpha, eps)  # eq. 50-52
            q = normalize_scalar(multiply_scalar(dqs, q))  # eq. 53
            diag[0] = alpha
            diag[6] = 1.0 if slerp else 0.0
            if mag_ok:
                # 4. magnetometer delta quaternion (eq. 54-58), heading only
                lx, ly, _ = rotate_scalar(q, (mag[0], mag[1], mag[2]))
                gam = lx * lx + ly * ly
                if gam > 1e-18:
                    sg = math.sqrt(gam)
                    den = gam + ly * sg
                    if den > 1e-12 * gam:
                        dqm = (math.sqrt(den / (2.0 * gam)), 0.0, 0.0, lx / math.sqrt(2.0 * den))
                    else:  # l points south: 180° about the vertical
                        dqm = (0.0, 0.0, 0.0, 1.0)
                    dqms, _ = scale_delta_quat(dqm, gain_mag, eps)  # eq. 59
                    q = normalize_scalar(multiply_scalar(dqms, q))
                    diag[5] = 1.0
        store_quat(state, q)
    if gyr_ok:
        state[8], state[9], state[10] = gyr[0], gyr[1], gyr[2]
        state[11] = 1.0
    diag[2], diag[3], diag[4] = state[5], state[6], state[7]


class AquaFilter(OrientationFilter):
    """AQUA (Valenti et al. 2015): ``AquaFilter(fs, tau_acc=11.66, tau_mag=70.0)`` (τ in s)."""

    name = "aqua"
    Settings = AquaSettings
    Coefficients = AquaCoefficients
    state_names = ("bias_x", "bias_y", "bias_z", "prev_gyr_x", "prev_gyr_y", "prev_gyr_z", "prev_gyr_valid")
    diagnostic_names = ("alpha", "steady", "bias_x", "bias_y", "bias_z", "mag_used", "slerp")
    step = aqua_step

    def _coefficients(self) -> dict:
        s = self.settings
        per_sample = {"gain_acc": s.tau_acc, "gain_mag": s.tau_mag, "bias_alpha": s.bias_tau}
        own = {f: (gain(per_sample[f], self.Ts) if f in per_sample else getattr(s, f))
               for f in AquaCoefficients._fields[2:]}  # the others named as the settings
        own.update(adaptive=float(s.adaptive), estimate_bias=float(s.estimate_bias))
        return own
