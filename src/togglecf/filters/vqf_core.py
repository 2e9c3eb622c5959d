"""VQF core: the orientation filter of Laidig & Seel, written from the paper's equations.

D. Laidig, T. Seel, "VQF: Highly accurate IMU orientation estimation with bias estimation and
magnetic disturbance rejection", Information Fusion 91:187-204, 2023 (arXiv 2203.17024).
Comments ``# Alg. 1 l. N`` cite the line of the paper's Algorithm 1 (basic VQF); the extensions
(rest detection, bias estimation, magnetic disturbance rejection) are cited by the paper's topic
and by the labelled equations (R1)…(M9) below, which spell out what the code computes.

Frames (ENU earth, quaternions sensor -> frame, ``[w, x, y, z]``, Hamilton):
ς sensor, I almost-inertial frame of pure strapdown integration, εᵢ 6D earth frame (heading
drifts), ε 9D earth frame. State: ``q_gyr`` (ς -> I), ``q_acc`` (I -> εᵢ), heading offset δ.

Per sample (gyro, then acc, then mag, as VQF):

Gyroscope
  (R1) rest LP:  ω̄ = LP₂(ω; τ_rest);  rest candidate while ‖ω − ω̄‖² < th_ω² and every
       |ω̄ᵢ| ≤ b_clip; the rest timer counts Ts per candidate sample, rest once it reaches
       t_rest,min; any failure (here or in (R2)) resets timer and flag
  Alg. 1 l. 8   q_gyr ← q_gyr ⊗ exp((ω − b̂) Δt / 2)     (actual Δt of the sample)

Accelerometer
  (R2) rest LP:  ā = LP₂(a; τ_rest); ‖a − ā‖² ≥ th_a² ends rest
  Alg. 1 l. 9   [a]_I = q_gyr ⊗ a ⊗ q_gyr*
  Alg. 1 l. 10  [a_LP]_I = LP₂([a]_I; τ_acc)   second-order Butterworth (below)
  Alg. 1 l. 11  [a_LP]_εᵢ = q_acc ⊗ [a_LP]_I ⊗ q_acc*
  Alg. 1 l. 12  (a_x, a_y, a_z) = [a_LP]_εᵢ / ‖[a_LP]_εᵢ‖
  Alg. 1 l. 13  q_w = √((a_z + 1)/2)
  Alg. 1 l. 14  q_acc ← [q_w, a_y/(2q_w), −a_x/(2q_w), 0] ⊗ q_acc   (rotates a onto +z)
  Alg. 1 l. 15  q_6D = q_acc ⊗ q_gyr
  Gyro bias, Kalman filter on b (3) with covariance P (3×3):
  (B1) predict:  P_ii ← P_ii + V   for each i with P_ii < P₀  (P never exceeds its initial value)
  (B2) at rest:  y = ω̄ (rest LP of the gyro),  model y = b,  W = W_rest I
  (B3) in motion: the correction of l. 14 turns εᵢ at the earth-frame rate
       ω_c = (a_y, −a_x, 0)/Ts. A bias error Δb = b − b̂ turns the strapdown estimate at R Δb
       (R = R(q_6D)), and the correction cancels it in steady state: R Δb = −ω_c (x, y). Since
       ω_c comes out of the τ_acc low-pass, R and R b̂ pass the same low-pass (R̄ = LP₂(R),
       (R b̂)‾ = LP₂(R b̂)): e = y − R̄ b̂ with
           e_x = −a_y/Ts + (R b̂)‾_x − R̄_x· b̂,   e_y = a_x/Ts + (R b̂)‾_y − R̄_y· b̂,
           e_z = −R̄_z· b̂   (pseudo-measurement 0 of the vertical bias, unobservable by gravity)
       W = diag(W_motion, W_motion, W_motion / f_vertical)
  (B4) update (innovation clipped to ±b_clip): K = P Mᵀ (M P Mᵀ + W)⁻¹, b̂ ← b̂ + K e,
       P ← P − K M P   (M = R̄ in motion, I at rest); finally b̂ clipped to ±b_clip per axis
  (B5) noises from physical standard deviations: P₀ = σ_init²; V = (0.1 °/s)² Ts / T_forget
       (the bias may drift by 0.1 °/s within the forgetting time); W is chosen so that the
       steady-state posterior variance of a scalar filter with process noise V is σ²:
       P = (P + V) W / (P + V + W)  ⇔  W = σ⁴/V + σ²   (σ = σ_motion or σ_rest)

Magnetometer (9D)
  Alg. 1 l. 17  [m]_εᵢ = q_6D ⊗ m ⊗ q_6D*
  (M1) field norm n = ‖[m]_εᵢ‖ and dip d = −asin(m_z / n), low-passed with τ_mag,current
  (M2) undisturbed iff |n − n_ref| < th_n n_ref and |d − d_ref| < th_dip; after
       t_undisturbed,min of that, the disturbance flag clears and (n_ref, d_ref) track (n, d)
       with the first-order gain k_ref (τ_mag,ref); any violation sets the flag
  (M3) new field acceptance: a candidate (n_c, d_c) tracks (n, d) with k_ref while (n, d) stays
       within the same thresholds of it (else it restarts at (n, d)); its timer grows only
       while ‖ω̄‖ ≥ ω_new,min (the sensor turns, so a field that stays the same is the earth's);
       while disturbed, the candidate becomes the reference after t_new (t_new,first when
       there has never been a reference)
  Alg. 1 l. 18  δ_mag = atan2(m_x, m_y)
  Alg. 1 l. 19  δ ← δ + k wrap(δ_mag − δ), k = k_mag = 1 − exp(−Ts/τ_mag), except:
  (M4) rejection: while disturbed, k = 0 for up to t_reject,max (the rejection timer counts
       up); past that, k = k_mag / f_reject; undisturbed, the timer counts down f_reject
       times faster
  (M5) start-up: k ≥ 1/N for the N-th magnetometer sample, until 1/N·τ_mag < Ts
  Alg. 1 l. 21  q_9D = [cos(δ/2), 0, 0, sin(δ/2)] ⊗ q_6D

Second-order Butterworth LP₂(·; τ): cut-off f_c = √2/(2πτ), bilinear transform with
pre-warping, C = tan(π f_c Ts): b₀ = b₂ = C²/D, b₁ = 2b₀, a₁ = 2(C² − 1)/D, a₂ = (1 − √2C + C²)/D,
D = 1 + √2C + C², run in a "delta" form (``_lp``: level and increment, the same transfer
function as VQF's direct form II transposed, whose state would kick the output when the learned
filter changes τ_acc). To not depend on the first sample, each filter outputs the running mean of
its inputs for its first τ seconds and then starts in the steady state of that mean.

Bad samples (policy of ``filters.base``): a non-finite/saturated gyro or an invalid Δt skips
the gyro part (rest LP and timer, strapdown); an invalid accelerometer sample skips the whole
accelerometer part (rest LP, inclination correction, bias estimation); an invalid magnetometer
sample skips the heading part. No invalid value reaches the state.

Units of the settings follow VQF's (°/s, °, s, m/s²); the coefficients are converted to rad.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
from numba import njit

from togglecf.core.quaternion import from_rotvec_scalar, multiply_scalar, rotate_scalar
from togglecf.filters.base import FilterSettings, OrientationFilter, dt_valid, gyro_valid, vector_ok

__all__ = [
    "VQFCoreCoefficients",
    "CoreModulation",
    "core_update",
    "base_modulation",
    "bias_noise_w",
    "VQFCoreFilter",
    "VQFCoreSettings",
    "butterworth_lp_coefficients",
    "gain_from_tau",
]

_DEG = math.pi / 180.0
#: VQF's bias random-walk scale: the bias may change by this much [°/s] within ``bias_forgetting_time``
_BIAS_DRIFT_DEG_S = 0.1


@dataclass(frozen=True)
class VQFCoreSettings(FilterSettings):
    """VQF's parameters (same names in snake_case, same defaults, same units).

    Attributes:
        tau_acc: τ_acc [s], time constant of the accelerometer low-pass in the almost-inertial
            frame (inclination correction and motion bias estimation). Default 3.0.
        tau_mag: τ_mag [s], time constant of the heading correction (0: take every sample as
            is). Default 9.0.
        motion_bias_est_enabled: estimate the gyro bias in motion (B3). Default True.
        rest_bias_est_enabled: detect rest and estimate the gyro bias at rest (R1, R2, B2).
            Default True.
        mag_dist_rejection_enabled: detect and reject magnetic disturbances (M1-M4). Default True.
        bias_sigma_init: σ_init [°/s], standard deviation of the initial bias estimate. Default 0.5.
        bias_forgetting_time: T_forget [s], time in which the bias uncertainty grows by
            0.1 °/s (sets the process noise V). Default 100.0.
        bias_clip: b_clip [°/s], largest bias estimate and innovation per axis; a rest-LP gyro
            axis beyond it is not rest. Default 2.0.
        bias_sigma_motion: σ_motion [°/s], steady-state standard deviation of the bias estimate
            in motion (sets W_motion). Default 0.1.
        bias_vertical_forgetting_factor: f_vertical (dimensionless), the vertical axis' motion
            measurement noise is W_motion / f_vertical. Default 0.0001.
        bias_sigma_rest: σ_rest [°/s], steady-state standard deviation of the bias estimate at
            rest (sets W_rest). Default 0.03.
        rest_min_t: t_rest,min [s], time the rest thresholds must hold before rest. Default 1.5.
        rest_filter_tau: τ_rest [s], time constant of the rest-detection low-passes. Default 0.5.
        rest_th_gyr: th_ω [°/s], largest deviation of ω from its low-pass at rest. Default 2.0.
        rest_th_acc: th_a [m/s²], largest deviation of a from its low-pass at rest. Default 0.5.
        mag_current_tau: τ_mag,current [s], low-pass of the field norm and dip (0: none).
            Default 0.05.
        mag_ref_tau: τ_mag,ref [s], time constant with which the reference norm and dip track
            an undisturbed field. Default 20.0.
        mag_norm_th: th_n (dimensionless), largest relative deviation of the field norm from
            the reference. Default 0.1.
        mag_dip_th: th_dip [°], largest deviation of the dip angle from the reference. Default 10.0.
        mag_new_time: t_new [s], time of (rotating) agreement after which a new field is
            accepted. Default 20.0.
        mag_new_first_time: t_new,first [s], the same while there has never been a reference.
            Default 5.0.
        mag_new_min_gyr: ω_new,min [°/s], smallest rest-LP rate at which the candidate timer
            runs. Default 20.0.
        mag_min_undisturbed_time: t_undisturbed,min [s], time of agreement before the
            disturbance flag clears. Default 0.5.
        mag_max_rejection_time: t_reject,max [s], longest stretch with the magnetometer fully
            rejected. Default 60.0.
        mag_rejection_factor: f_reject (dimensionless), gain divisor once the rejection time is
            used up, and the speed-up of the rejection timer's count-down. Default 2.0.
    """

    tau_acc: float = 3.0
    tau_mag: float = 9.0
    motion_bias_est_enabled: bool = True
    rest_bias_est_enabled: bool = True
    mag_dist_rejection_enabled: bool = True
    bias_sigma_init: float = 0.5
    bias_forgetting_time: float = 100.0
    bias_clip: float = 2.0
    bias_sigma_motion: float = 0.1
    bias_vertical_forgetting_factor: float = 0.0001
    bias_sigma_rest: float = 0.03
    rest_min_t: float = 1.5
    rest_filter_tau: float = 0.5
    rest_th_gyr: float = 2.0
    rest_th_acc: float = 0.5
    mag_current_tau: float = 0.05
    mag_ref_tau: float = 20.0
    mag_norm_th: float = 0.1
    mag_dip_th: float = 10.0
    mag_new_time: float = 20.0
    mag_new_first_time: float = 5.0
    mag_new_min_gyr: float = 20.0
    mag_min_undisturbed_time: float = 0.5
    mag_max_rejection_time: float = 60.0
    mag_rejection_factor: float = 2.0

    def __post_init__(self):
        super().__post_init__()
        for k in ("tau_acc", "rest_filter_tau", "bias_sigma_init", "bias_forgetting_time", "bias_sigma_motion",
                  "bias_sigma_rest", "mag_rejection_factor"):
            if not getattr(self, k) > 0:
                raise ValueError(f"{k} must be > 0, got {getattr(self, k)}")
        for k in ("tau_mag", "bias_clip", "bias_vertical_forgetting_factor", "rest_min_t", "rest_th_gyr",
                  "rest_th_acc", "mag_current_tau", "mag_ref_tau", "mag_norm_th", "mag_dip_th", "mag_new_time",
                  "mag_new_first_time", "mag_new_min_gyr", "mag_min_undisturbed_time", "mag_max_rejection_time"):
            if not getattr(self, k) >= 0:
                raise ValueError(f"{k} must be >= 0, got {getattr(self, k)}")


class VQFCoreCoefficients(NamedTuple):
    """Per-sample coefficients (from the settings and ``Ts``), passed to the kernel as ``params``.
    Angles and rates in rad, rad/s; covariances in (rad/s)²; flags 1.0/0.0."""

    use_mag: float
    max_dt: float
    ts: float  # nominal sampling time Ts [s]
    inv_ts: float  # 1/Ts [1/s]
    tau_acc: float
    acc_b0: float
    acc_b1: float
    acc_b2: float
    acc_a1: float
    acc_a2: float
    k_mag: float
    tau_mag: float
    motion_bias: float
    rest_bias: float
    mag_rejection: float
    bias_p0: float
    bias_v: float
    bias_w_motion: float
    bias_w_vertical: float
    bias_w_rest: float
    bias_clip: float
    rest_tau: float
    rest_b0: float
    rest_b1: float
    rest_b2: float
    rest_a1: float
    rest_a2: float
    rest_th_gyr_sq: float
    rest_th_acc_sq: float
    rest_min_t: float
    mag_cur_tau: float
    mag_b0: float
    mag_b1: float
    mag_b2: float
    mag_a1: float
    mag_a2: float
    k_mag_ref: float
    mag_norm_th: float
    mag_dip_th: float
    mag_new_time: float
    mag_new_first_time: float
    mag_new_min_gyr_sq: float  # ω_new,min² [(rad/s)²]
    mag_min_undisturbed_t: float
    mag_max_rejection_t: float
    mag_rejection_factor: float


class CoreModulation(NamedTuple):
    """The coefficients a learned filter may change from sample to sample (``filters.vqf_toggling``);
    the core itself runs them at their settings' values (``base_modulation``). Same units as in
    ``VQFCoreCoefficients``."""

    acc_b0: float  # τ_acc low-pass (second-order Butterworth) ...
    acc_b1: float
    acc_b2: float
    acc_a1: float
    acc_a2: float  # ... coefficients
    k_mag: float  # heading gain per sample, 1 − exp(−Ts/τ_mag)
    bias_w_motion: float  # W_motion of the bias estimation in motion [(rad/s)²]
    bias_w_vertical: float  # its vertical-axis counterpart
    rest_th_gyr_sq: float  # th_ω² [(rad/s)²]
    rest_th_acc_sq: float  # th_a² [(m/s²)²]


@njit(cache=True)
def butterworth_lp_coefficients(tau: float, ts: float) -> tuple[float, float, float, float, float]:
    """``(b0, b1, b2, a1, a2)`` of the second-order Butterworth low-pass with time constant
    ``tau`` [s] at sampling time ``ts`` [s] (module docstring; ``a0 = 1``)."""
    fc = math.sqrt(2.0) / (2.0 * math.pi * tau)
    c = math.tan(math.pi * fc * ts)
    d = c * c + math.sqrt(2.0) * c + 1.0
    b0 = c * c / d
    return b0, 2.0 * b0, b0, 2.0 * (c * c - 1.0) / d, (1.0 - math.sqrt(2.0) * c + c * c) / d


@njit(cache=True)
def gain_from_tau(tau: float, ts: float) -> float:
    """Per-sample gain of a first-order low-pass with time constant ``tau`` [s]: 1 − exp(−Ts/τ)
    (1 for τ = 0)."""
    return 1.0 if tau == 0.0 else 1.0 - math.exp(-ts / tau)


@njit(cache=True)
def bias_noise_w(sigma: float, v: float) -> float:
    """(B5): measurement noise W [(rad/s)²] whose steady-state posterior standard deviation is
    ``sigma`` [rad/s] with process noise ``v`` per sample: W = σ⁴/V + σ²."""
    s2 = sigma * sigma
    return s2 * s2 / v + s2


# ------------------------------------------------------------------------------------------
# State layout: state[0:4] output quaternion, state[4] initialised; then these, in order.
# A low-pass bank of C channels is [n, ready, (s0, s1) × C]: while averaging (ready = 0), n is
# the number of samples so far and s0 the running sum of the channel.
# ------------------------------------------------------------------------------------------

def _bank(name, channels):
    return (f"{name}_n", f"{name}_ready") + tuple(f"{name}_{c}_{s}" for c in channels for s in ("s0", "s1"))


_XYZ = ("x", "y", "z")
_STATE_NAMES = (
    ("q_gyr_w", "q_gyr_x", "q_gyr_y", "q_gyr_z", "q_acc_w", "q_acc_x", "q_acc_y", "q_acc_z", "delta",
     "bias_x", "bias_y", "bias_z")
    + tuple(f"bias_p{i}{j}" for i in range(3) for j in range(3))
    + ("rest_detected", "rest_t", "rest_gyr_lp_x", "rest_gyr_lp_y", "rest_gyr_lp_z",
       "mag_dist_detected", "mag_ref_norm", "mag_ref_dip", "mag_undisturbed_t", "mag_reject_t",
       "mag_cand_norm", "mag_cand_dip", "mag_cand_t", "k_mag_init")
    + _bank("acc_lp", _XYZ)
    + _bank("rest_gyr_bank", _XYZ)
    + _bank("rest_acc_bank", _XYZ)
    + _bank("bias_r_lp", tuple(f"r{i}{j}" for i in range(3) for j in range(3)))
    + _bank("bias_rb_lp", ("x", "y"))
    + _bank("mag_nd_lp", ("norm", "dip"))
)
_IDX = {n: 5 + i for i, n in enumerate(_STATE_NAMES)}
O_QGYR = _IDX["q_gyr_w"]
O_QACC = _IDX["q_acc_w"]
O_DELTA = _IDX["delta"]
O_BIAS = _IDX["bias_x"]
O_P = _IDX["bias_p00"]
O_REST = _IDX["rest_detected"]
O_REST_T = _IDX["rest_t"]
O_GYR_LP = _IDX["rest_gyr_lp_x"]
O_MAG_DIST = _IDX["mag_dist_detected"]
O_MAG_REF_NORM = _IDX["mag_ref_norm"]
O_MAG_REF_DIP = _IDX["mag_ref_dip"]
O_MAG_UNDIST_T = _IDX["mag_undisturbed_t"]
O_MAG_REJECT_T = _IDX["mag_reject_t"]
O_MAG_CAND_NORM = _IDX["mag_cand_norm"]
O_MAG_CAND_DIP = _IDX["mag_cand_dip"]
O_MAG_CAND_T = _IDX["mag_cand_t"]
O_K_MAG_INIT = _IDX["k_mag_init"]
B_ACC = _IDX["acc_lp_n"]
B_RGYR = _IDX["rest_gyr_bank_n"]
B_RACC = _IDX["rest_acc_bank_n"]
B_R = _IDX["bias_r_lp_n"]
B_RB = _IDX["bias_rb_lp_n"]
B_MAG = _IDX["mag_nd_lp_n"]

_DIAG_NAMES = ("rest", "mag_dist", "bias_x", "bias_y", "bias_z", "bias_sigma", "delta", "k_mag")


# ------------------------------------------------------------------------------------------
# Kernel building blocks
# ------------------------------------------------------------------------------------------

@njit(cache=True, inline="always")
def _lp_begin(state, off):
    """Start a sample of the LP bank at ``off``: ``(ready, n)``, counting the sample while averaging."""
    if state[off + 1] > 0.5:
        return True, 0.0
    n = state[off] + 1.0
    state[off] = n
    return False, n


@njit(cache=True, inline="always")
def _lp(state, i, x, ready, n, b0, b1, b2, a1, a2):
    """One channel (state[i], state[i+1]) = (v, dv) of the second-order LP
    H(z) = b0 (1 + z⁻¹)² / (1 + a1 z⁻¹ + a2 z⁻²) with unit DC gain: the output for input ``x``.

    Delta form (as the C core, ``embedded/tcf_vqf.c``): with K = 4 b0 = 1 + a1 + a2 and
    β = 1 − a2, v the level and dv its last increment,
        dv_k = (1 − β) dv_{k−1} + K (x_k − v_{k−1}),   v_k = v_{k−1} + dv_k,
        y_k  = v_{k−1} + (dv_k − dv_{k−1}) / 4.
    The same transfer function as VQF's direct form II transposed, but its state is the
    signal itself (level and increment), not a coefficient-dependent mix: when the learned
    filter changes τ_acc between samples (``filters.vqf_toggling``) the output continues
    smoothly, where the DF2T state run on with new coefficients kicks the output (measured
    4.2 m/s² on the low-passed gravity for a 3 s -> 1 s switch). ``b1``, ``a1`` are implied."""
    if ready:
        dv = a2 * state[i + 1] + 4.0 * b0 * (x - state[i])  # (1 − β) = a2
        y = state[i] + 0.25 * (dv - state[i + 1])
        state[i] += dv
        state[i + 1] = dv
        return y
    state[i] += x  # averaging phase: running sum, output the mean
    return state[i] / n


@njit(cache=True, inline="always")
def _lp_end(state, off, nch, ready, n, tau, ts, b0, b2, a2):
    """End of the averaging phase after τ: start each channel in the steady state of its mean
    (v = mean, dv = 0)."""
    if (not ready) and n * ts >= tau:
        for c in range(nch):
            i = off + 2 + 2 * c
            state[i] = state[i] / n
            state[i + 1] = 0.0
        state[off + 1] = 1.0


@njit(cache=True, inline="always")
def _wrap(a):
    if a > math.pi:
        return a - 2.0 * math.pi
    if a < -math.pi:
        return a + 2.0 * math.pi
    return a


@njit(cache=True, inline="always")
def _clip(x, lim):
    return min(max(x, -lim), lim)


@njit(cache=True, inline="always")
def _unit(q):
    """q / ‖q‖ for a 4-tuple (one division); identity for a zero or non-finite norm."""
    n = math.sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3])
    if not (n > 1e-12 and n < math.inf):
        return (1.0, 0.0, 0.0, 0.0)
    r = 1.0 / n
    return (q[0] * r, q[1] * r, q[2] * r, q[3] * r)


@njit(cache=True, inline="always")
def _quat(state, off):
    return (state[off], state[off + 1], state[off + 2], state[off + 3])


@njit(cache=True, inline="always")
def _matrix(q):
    """Row-major rotation matrix (9-tuple) of unit quaternion q (sensor -> earth)."""
    w, x, y, z = q
    return (1.0 - 2.0 * (y * y + z * z), 2.0 * (x * y - w * z), 2.0 * (x * z + w * y),
            2.0 * (x * y + w * z), 1.0 - 2.0 * (x * x + z * z), 2.0 * (y * z - w * x),
            2.0 * (x * z - w * y), 2.0 * (y * z + w * x), 1.0 - 2.0 * (x * x + y * y))


@njit(cache=True, inline="always")
def _mm(a, b):
    """A B for row-major 9-tuples."""
    return (a[0] * b[0] + a[1] * b[3] + a[2] * b[6], a[0] * b[1] + a[1] * b[4] + a[2] * b[7],
            a[0] * b[2] + a[1] * b[5] + a[2] * b[8],
            a[3] * b[0] + a[4] * b[3] + a[5] * b[6], a[3] * b[1] + a[4] * b[4] + a[5] * b[7],
            a[3] * b[2] + a[4] * b[5] + a[5] * b[8],
            a[6] * b[0] + a[7] * b[3] + a[8] * b[6], a[6] * b[1] + a[7] * b[4] + a[8] * b[7],
            a[6] * b[2] + a[7] * b[5] + a[8] * b[8])


@njit(cache=True, inline="always")
def _mmt(a, b):
    """A Bᵀ for row-major 9-tuples."""
    return (a[0] * b[0] + a[1] * b[1] + a[2] * b[2], a[0] * b[3] + a[1] * b[4] + a[2] * b[5],
            a[0] * b[6] + a[1] * b[7] + a[2] * b[8],
            a[3] * b[0] + a[4] * b[1] + a[5] * b[2], a[3] * b[3] + a[4] * b[4] + a[5] * b[5],
            a[3] * b[6] + a[4] * b[7] + a[5] * b[8],
            a[6] * b[0] + a[7] * b[1] + a[8] * b[2], a[6] * b[3] + a[7] * b[4] + a[8] * b[5],
            a[6] * b[6] + a[7] * b[7] + a[8] * b[8])


@njit(cache=True, inline="always")
def _bias_predict(state, p):
    """(B1): P_ii ← P_ii + V while P_ii < P₀ (also without a measurement)."""
    for i in range(3):
        j = O_P + 4 * i
        if state[j] < p.bias_p0:
            state[j] += p.bias_v


@njit(cache=True, inline="always")
def _bias_update(state, p, ex, ey, ez, pmt, s):
    """(B4) with ``pmt`` = P Mᵀ and ``s`` = M P Mᵀ + W (9-tuples, s symmetric): K = P Mᵀ S⁻¹,
    b̂ ← b̂ + K e (e clipped to ±b_clip), P ← P − K M P = P − K (P Mᵀ)ᵀ (P is symmetric)."""
    # S⁻¹ by the adjugate; S is symmetric positive definite (W > 0), so only 6 cofactors
    c00 = s[4] * s[8] - s[5] * s[5]
    c01 = s[5] * s[2] - s[1] * s[8]
    c02 = s[1] * s[5] - s[4] * s[2]
    det = s[0] * c00 + s[1] * c01 + s[2] * c02
    if not (det > 0.0 and math.isfinite(det)):
        return
    d = 1.0 / det
    i00, i01, i02 = c00 * d, c01 * d, c02 * d
    i11 = (s[0] * s[8] - s[2] * s[2]) * d
    i12 = (s[2] * s[1] - s[0] * s[5]) * d
    i22 = (s[0] * s[4] - s[1] * s[1]) * d
    k = _mmt(pmt, (i00, i01, i02, i01, i11, i12, i02, i12, i22))  # P Mᵀ S⁻¹ (S⁻¹ symmetric)
    clip = p.bias_clip
    e0, e1, e2 = _clip(ex, clip), _clip(ey, clip), _clip(ez, clip)
    state[O_BIAS] += k[0] * e0 + k[1] * e1 + k[2] * e2
    state[O_BIAS + 1] += k[3] * e0 + k[4] * e1 + k[5] * e2
    state[O_BIAS + 2] += k[6] * e0 + k[7] * e1 + k[8] * e2
    kmp = _mmt(k, pmt)  # K (P Mᵀ)ᵀ = K M P
    for i in range(9):
        state[O_P + i] -= kmp[i]


@njit(cache=True, inline="always")
def _clip_bias(state, p):
    for i in range(3):
        state[O_BIAS + i] = _clip(state[O_BIAS + i], p.bias_clip)


# ------------------------------------------------------------------------------------------
# The step
# ------------------------------------------------------------------------------------------

@njit(cache=True, inline="always")
def core_update(state, p, mod, gyr, acc, mag, dt, diag):
    """One sample of the VQF core (module docstring) with coefficients ``p`` and the modulated
    ones ``mod`` (a ``CoreModulation``). diag: see ``VQFCoreFilter.diagnostic_names``."""
    ts = p.ts
    rest_bias = p.rest_bias > 0.5
    rest_lp_on = rest_bias or p.mag_rejection > 0.5

    # ---------------- gyroscope ----------------
    # policy of filters.base: a non-finite or saturated reading or an invalid Δt is neither
    # integrated nor learnt from (the rest low-pass feeds the rest bias measurement)
    if gyro_valid(gyr) and dt_valid(dt, p.max_dt):
        if rest_lp_on:  # (R1)
            ready, n = _lp_begin(state, B_RGYR)
            g0 = _lp(state, B_RGYR + 2, gyr[0], ready, n, p.rest_b0, p.rest_b1, p.rest_b2, p.rest_a1, p.rest_a2)
            g1 = _lp(state, B_RGYR + 4, gyr[1], ready, n, p.rest_b0, p.rest_b1, p.rest_b2, p.rest_a1, p.rest_a2)
            g2 = _lp(state, B_RGYR + 6, gyr[2], ready, n, p.rest_b0, p.rest_b1, p.rest_b2, p.rest_a1, p.rest_a2)
            _lp_end(state, B_RGYR, 3, ready, n, p.rest_tau, ts, p.rest_b0, p.rest_b2, p.rest_a2)
            state[O_GYR_LP], state[O_GYR_LP + 1], state[O_GYR_LP + 2] = g0, g1, g2
            d0, d1, d2 = gyr[0] - g0, gyr[1] - g1, gyr[2] - g2
            if (d0 * d0 + d1 * d1 + d2 * d2 >= mod.rest_th_gyr_sq or abs(g0) > p.bias_clip
                    or abs(g1) > p.bias_clip or abs(g2) > p.bias_clip):
                state[O_REST_T] = 0.0
                state[O_REST] = 0.0
            else:
                state[O_REST_T] += ts
                if state[O_REST_T] >= p.rest_min_t:
                    state[O_REST] = 1.0
        # Alg. 1 l. 8: strapdown integration of the bias-corrected rate over the actual Δt
        dq = from_rotvec_scalar((gyr[0] - state[O_BIAS]) * dt, (gyr[1] - state[O_BIAS + 1]) * dt,
                                (gyr[2] - state[O_BIAS + 2]) * dt)
        qg = _unit(multiply_scalar(_quat(state, O_QGYR), dq))
        state[O_QGYR], state[O_QGYR + 1], state[O_QGYR + 2], state[O_QGYR + 3] = qg

    # ---------------- accelerometer ----------------
    q6 = (1.0, 0.0, 0.0, 0.0)
    have_q6 = False  # q_6D is computed once per sample, in the bias estimation when it runs
    if vector_ok(acc):
        if rest_bias:  # (R2)
            ready, n = _lp_begin(state, B_RACC)
            l0 = _lp(state, B_RACC + 2, acc[0], ready, n, p.rest_b0, p.rest_b1, p.rest_b2, p.rest_a1, p.rest_a2)
            l1 = _lp(state, B_RACC + 4, acc[1], ready, n, p.rest_b0, p.rest_b1, p.rest_b2, p.rest_a1, p.rest_a2)
            l2 = _lp(state, B_RACC + 6, acc[2], ready, n, p.rest_b0, p.rest_b1, p.rest_b2, p.rest_a1, p.rest_a2)
            _lp_end(state, B_RACC, 3, ready, n, p.rest_tau, ts, p.rest_b0, p.rest_b2, p.rest_a2)
            d0, d1, d2 = acc[0] - l0, acc[1] - l1, acc[2] - l2
            if d0 * d0 + d1 * d1 + d2 * d2 >= mod.rest_th_acc_sq:
                state[O_REST_T] = 0.0
                state[O_REST] = 0.0
        ai = rotate_scalar(_quat(state, O_QGYR), (acc[0], acc[1], acc[2]))  # Alg. 1 l. 9
        ready, n = _lp_begin(state, B_ACC)  # Alg. 1 l. 10
        f0 = _lp(state, B_ACC + 2, ai[0], ready, n, mod.acc_b0, mod.acc_b1, mod.acc_b2, mod.acc_a1, mod.acc_a2)
        f1 = _lp(state, B_ACC + 4, ai[1], ready, n, mod.acc_b0, mod.acc_b1, mod.acc_b2, mod.acc_a1, mod.acc_a2)
        f2 = _lp(state, B_ACC + 6, ai[2], ready, n, mod.acc_b0, mod.acc_b1, mod.acc_b2, mod.acc_a1, mod.acc_a2)
        _lp_end(state, B_ACC, 3, ready, n, p.tau_acc, ts, mod.acc_b0, mod.acc_b2, mod.acc_a2)
        qa = _quat(state, O_QACC)
        ae = rotate_scalar(qa, (f0, f1, f2))  # Alg. 1 l. 11
        na = math.sqrt(ae[0] * ae[0] + ae[1] * ae[1] + ae[2] * ae[2])
        if na > 0.0 and na < math.inf:
            rn = 1.0 / na
            ax, ay, az = ae[0] * rn, ae[1] * rn, ae[2] * rn  # Alg. 1 l. 12
            qw = math.sqrt(max(0.5 * (az + 1.0), 0.0))  # Alg. 1 l. 13
            if qw > 1e-6:  # Alg. 1 l. 14
                h = 0.5 / qw
                corr = (qw, ay * h, -ax * h, 0.0)
            else:  # a points down: the 180° correction about any horizontal axis
                corr = (0.0, 1.0, 0.0, 0.0)
            qa = _unit(multiply_scalar(corr, qa))
            state[O_QACC], state[O_QACC + 1], state[O_QACC + 2], state[O_QACC + 3] = qa
            state[4] = 1.0

            if rest_bias or p.motion_bias > 0.5:  # gyro bias estimation (B1)-(B5)
                b0, b1, b2 = state[O_BIAS], state[O_BIAS + 1], state[O_BIAS + 2]
                q6 = multiply_scalar(qa, _quat(state, O_QGYR))  # Alg. 1 l. 15
                have_q6 = True
                r = _matrix(q6)  # R(q_6D)
                rb0 = r[0] * b0 + r[1] * b1 + r[2] * b2
                rb1 = r[3] * b0 + r[4] * b1 + r[5] * b2
                ready, n = _lp_begin(state, B_R)  # R̄ = LP₂(R; τ_acc)
                r00 = _lp(state, B_R + 2, r[0], ready, n, mod.acc_b0, mod.acc_b1, mod.acc_b2, mod.acc_a1, mod.acc_a2)
                r01 = _lp(state, B_R + 4, r[1], ready, n, mod.acc_b0, mod.acc_b1, mod.acc_b2, mod.acc_a1, mod.acc_a2)
                r02 = _lp(state, B_R + 6, r[2], ready, n, mod.acc_b0, mod.acc_b1, mod.acc_b2, mod.acc_a1, mod.acc_a2)
                r10 = _lp(state, B_R + 8, r[3], ready, n, mod.acc_b0, mod.acc_b1, mod.acc_b2, mod.acc_a1, mod.acc_a2)
                r11 = _lp(state, B_R + 10, r[4], ready, n, mod.acc_b0, mod.acc_b1, mod.acc_b2, mod.acc_a1, mod.acc_a2)
                r12 = _lp(state, B_R + 12, r[5], ready, n, mod.acc_b0, mod.acc_b1, mod.acc_b2, mod.acc_a1, mod.acc_a2)
                r20 = _lp(state, B_R + 14, r[6], ready, n, mod.acc_b0, mod.acc_b1, mod.acc_b2, mod.acc_a1, mod.acc_a2)
                r21 = _lp(state, B_R + 16, r[7], ready, n, mod.acc_b0, mod.acc_b1, mod.acc_b2, mod.acc_a1, mod.acc_a2)
                r22 = _lp(state, B_R + 18, r[8], ready, n, mod.acc_b0, mod.acc_b1, mod.acc_b2, mod.acc_a1, mod.acc_a2)
                _lp_end(state, B_R, 9, ready, n, p.tau_acc, ts, mod.acc_b0, mod.acc_b2, mod.acc_a2)
                ready, n = _lp_begin(state, B_RB)  # (R b̂)‾ = LP₂(R b̂; τ_acc), x and y
                rb0 = _lp(state, B_RB + 2, rb0, ready, n, mod.acc_b0, mod.acc_b1, mod.acc_b2, mod.acc_a1, mod.acc_a2)
                rb1 = _lp(state, B_RB + 4, rb1, ready, n, mod.acc_b0, mod.acc_b1, mod.acc_b2, mod.acc_a1, mod.acc_a2)
                _lp_end(state, B_RB, 2, ready, n, p.tau_acc, ts, mod.acc_b0, mod.acc_b2, mod.acc_a2)
                _bias_predict(state, p)  # (B1)
                P = (state[O_P], state[O_P + 1], state[O_P + 2], state[O_P + 3], state[O_P + 4],
                     state[O_P + 5], state[O_P + 6], state[O_P + 7], state[O_P + 8])
                if rest_bias and state[O_REST] > 0.5:  # (B2): y = ω̄, M = I, P Mᵀ = P
                    w = p.bias_w_rest
                    _bias_update(state, p, state[O_GYR_LP] - b0, state[O_GYR_LP + 1] - b1,
                                 state[O_GYR_LP + 2] - b2, P,
                                 (P[0] + w, P[1], P[2], P[3], P[4] + w, P[5], P[6], P[7], P[8] + w))
                elif p.motion_bias > 0.5:  # (B3): M = R̄
                    ex = -ay * p.inv_ts + rb0 - (r00 * b0 + r01 * b1 + r02 * b2)
                    ey = ax * p.inv_ts + rb1 - (r10 * b0 + r11 * b1 + r12 * b2)
                    ez = -(r20 * b0 + r21 * b1 + r22 * b2)
                    m = (r00, r01, r02, r10, r11, r12, r20, r21, r22)
                    pmt = _mmt(P, m)  # P Mᵀ
                    s = _mm(m, pmt)  # M P Mᵀ
                    _bias_update(state, p, ex, ey, ez, pmt,
                                 (s[0] + mod.bias_w_motion, s[1], s[2], s[3], s[4] + mod.bias_w_motion, s[5],
                                  s[6], s[7], s[8] + mod.bias_w_vertical))
                _clip_bias(state, p)

    if not have_q6:
        q6 = multiply_scalar(_quat(state, O_QACC), _quat(state, O_QGYR))  # Alg. 1 l. 15
    k = 0.0

    # ---------------- magnetometer (9D) ----------------
    if p.use_mag > 0.5 and vector_ok(mag):
        me = rotate_scalar(q6, (mag[0], mag[1], mag[2]))  # Alg. 1 l. 17
        if p.mag_rejection > 0.5:
            nrm = math.sqrt(me[0] * me[0] + me[1] * me[1] + me[2] * me[2])  # (M1)
            dip = -math.asin(min(max(me[2] / nrm, -1.0), 1.0))
            if p.mag_cur_tau > 0.0:
                ready, n = _lp_begin(state, B_MAG)
                nrm = _lp(state, B_MAG + 2, nrm, ready, n, p.mag_b0, p.mag_b1, p.mag_b2, p.mag_a1, p.mag_a2)
                dip = _lp(state, B_MAG + 4, dip, ready, n, p.mag_b0, p.mag_b1, p.mag_b2, p.mag_a1, p.mag_a2)
                _lp_end(state, B_MAG, 2, ready, n, p.mag_cur_tau, ts, p.mag_b0, p.mag_b2, p.mag_a2)
            ref_n = state[O_MAG_REF_NORM]  # (M2)
            if abs(nrm - ref_n) < p.mag_norm_th * ref_n and abs(dip - state[O_MAG_REF_DIP]) < p.mag_dip_th:
                state[O_MAG_UNDIST_T] += ts
                if state[O_MAG_UNDIST_T] >= p.mag_min_undisturbed_t:
                    state[O_MAG_DIST] = 0.0
                    state[O_MAG_REF_NORM] += p.k_mag_ref * (nrm - ref_n)
                    state[O_MAG_REF_DIP] += p.k_mag_ref * (dip - state[O_MAG_REF_DIP])
            else:
                state[O_MAG_UNDIST_T] = 0.0
                state[O_MAG_DIST] = 1.0
            cand_n = state[O_MAG_CAND_NORM]  # (M3)
            if abs(nrm - cand_n) < p.mag_norm_th * cand_n and abs(dip - state[O_MAG_CAND_DIP]) < p.mag_dip_th:
                g0, g1, g2 = state[O_GYR_LP], state[O_GYR_LP + 1], state[O_GYR_LP + 2]
                if g0 * g0 + g1 * g1 + g2 * g2 >= p.mag_new_min_gyr_sq:  # ‖ω̄‖ ≥ ω_new,min
                    state[O_MAG_CAND_T] += ts
                state[O_MAG_CAND_NORM] += p.k_mag_ref * (nrm - cand_n)
                state[O_MAG_CAND_DIP] += p.k_mag_ref * (dip - state[O_MAG_CAND_DIP])
                if state[O_MAG_DIST] > 0.5 and (state[O_MAG_CAND_T] >= p.mag_new_time or (
                        state[O_MAG_REF_NORM] == 0.0 and state[O_MAG_CAND_T] >= p.mag_new_first_time)):
                    state[O_MAG_REF_NORM] = state[O_MAG_CAND_NORM]
                    state[O_MAG_REF_DIP] = state[O_MAG_CAND_DIP]
                    state[O_MAG_DIST] = 0.0
                    state[O_MAG_UNDIST_T] = p.mag_min_undisturbed_t
            else:
                state[O_MAG_CAND_T] = 0.0
                state[O_MAG_CAND_NORM] = nrm
                state[O_MAG_CAND_DIP] = dip
        dis = _wrap(math.atan2(me[0], me[1]) - state[O_DELTA])  # Alg. 1 l. 18-19
        k = mod.k_mag
        if p.mag_rejection > 0.5:  # (M4)
            if state[O_MAG_DIST] > 0.5:
                if state[O_MAG_REJECT_T] <= p.mag_max_rejection_t:
                    state[O_MAG_REJECT_T] += ts
                    k = 0.0
                else:
                    k = k / p.mag_rejection_factor
            else:
                state[O_MAG_REJECT_T] = max(state[O_MAG_REJECT_T] - p.mag_rejection_factor * ts, 0.0)
        kinit = state[O_K_MAG_INIT]  # (M5): k ≥ 1/N for the N-th sample while 1/N·τ_mag ≥ Ts
        if kinit != 0.0:
            k = max(k, kinit)
            kinit = kinit / (kinit + 1.0)
            state[O_K_MAG_INIT] = 0.0 if kinit * p.tau_mag < ts else kinit
        state[O_DELTA] = _wrap(state[O_DELTA] + k * dis)  # Alg. 1 l. 19

    # ---------------- output ----------------
    if p.use_mag > 0.5:  # Alg. 1 l. 21: q_9D = [cos δ/2, 0, 0, sin δ/2] ⊗ q_6D
        h = 0.5 * state[O_DELTA]
        c, s = math.cos(h), math.sin(h)
        q = (c * q6[0] - s * q6[3], c * q6[1] - s * q6[2], c * q6[2] + s * q6[1], c * q6[3] + s * q6[0])
    else:
        q = q6
    state[0], state[1], state[2], state[3] = q
    diag[0] = state[O_REST]
    diag[1] = state[O_MAG_DIST] if p.use_mag > 0.5 else 0.0
    diag[2] = state[O_BIAS]
    diag[3] = state[O_BIAS + 1]
    diag[4] = state[O_BIAS + 2]
    diag[5] = math.sqrt(max(state[O_P], state[O_P + 4], state[O_P + 8]))
    diag[6] = state[O_DELTA]
    diag[7] = k


@njit(cache=True, inline="always")
def base_modulation(p) -> "CoreModulation":
    """The modulated coefficients at their settings' values (the core without learning)."""
    return CoreModulation(p.acc_b0, p.acc_b1, p.acc_b2, p.acc_a1, p.acc_a2, p.k_mag, p.bias_w_motion,
                          p.bias_w_vertical, p.rest_th_gyr_sq, p.rest_th_acc_sq)


@njit(cache=True)
def vqf_core_step(state, params, gyr, acc, mag, dt, diag):
    """One sample of the VQF core (module docstring). diag: see ``VQFCoreFilter.diagnostic_names``."""
    core_update(state, params, base_modulation(params), gyr, acc, mag, dt, diag)


class VQFCoreFilter(OrientationFilter):
    """VQF core (module docstring): ``VQFCoreFilter(fs, use_mag=True, tau_acc=3.0, ...)``.

    Output: 9D quaternion ``q_9D`` (``use_mag=True``) or 6D ``q_6D`` (heading from the gyro
    only), sensor -> ENU. Diagnostics: ``rest`` (1.0 at rest), ``mag_dist`` (1.0 while the
    magnetic field is taken as disturbed), ``bias_x/y/z`` [rad/s], ``bias_sigma`` [rad/s]
    (√ of the largest variance of the bias estimate), ``delta`` [rad] (heading offset δ),
    ``k_mag`` (heading gain used this sample).
    """

    name = "vqf_core"
    Settings = VQFCoreSettings
    Coefficients = VQFCoreCoefficients
    state_names = _STATE_NAMES
    diagnostic_names = _DIAG_NAMES
    step = vqf_core_step

    def _coefficients(self) -> dict:
        s, ts = self.settings, self.Ts
        acc = butterworth_lp_coefficients(s.tau_acc, ts)
        rest = butterworth_lp_coefficients(s.rest_filter_tau, ts)
        mag = butterworth_lp_coefficients(s.mag_current_tau, ts) if s.mag_current_tau > 0 else (1.0, 0.0, 0.0, 0.0, 0.0)
        # (B5): variances in (rad/s)²
        p_motion = (s.bias_sigma_motion * _DEG) ** 2
        p_rest = (s.bias_sigma_rest * _DEG) ** 2
        v = (_BIAS_DRIFT_DEG_S * _DEG) ** 2 * ts / s.bias_forgetting_time
        w_motion = p_motion * p_motion / v + p_motion
        return {
            "ts": ts, "inv_ts": 1.0 / ts, "tau_acc": s.tau_acc, "acc_b0": acc[0], "acc_b1": acc[1], "acc_b2": acc[2], "acc_a1": acc[3], "acc_a2": acc[4],
            "k_mag": gain_from_tau(s.tau_mag, ts), "tau_mag": s.tau_mag,
            "motion_bias": float(s.motion_bias_est_enabled), "rest_bias": float(s.rest_bias_est_enabled),
            "mag_rejection": float(s.mag_dist_rejection_enabled),
            "bias_p0": (s.bias_sigma_init * _DEG) ** 2, "bias_v": v, "bias_w_motion": w_motion,
            "bias_w_vertical": w_motion / max(s.bias_vertical_forgetting_factor, 1e-10),
            "bias_w_rest": p_rest * p_rest / v + p_rest, "bias_clip": s.bias_clip * _DEG,
            "rest_tau": s.rest_filter_tau, "rest_b0": rest[0], "rest_b1": rest[1], "rest_b2": rest[2], "rest_a1": rest[3],
            "rest_a2": rest[4], "rest_th_gyr_sq": (s.rest_th_gyr * _DEG) ** 2, "rest_th_acc_sq": s.rest_th_acc ** 2,
            "rest_min_t": s.rest_min_t,
            "mag_cur_tau": s.mag_current_tau, "mag_b0": mag[0], "mag_b1": mag[1], "mag_b2": mag[2], "mag_a1": mag[3],
            "mag_a2": mag[4], "k_mag_ref": gain_from_tau(s.mag_ref_tau, ts), "mag_norm_th": s.mag_norm_th,
            "mag_dip_th": s.mag_dip_th * _DEG, "mag_new_time": s.mag_new_time, "mag_new_first_time": s.mag_new_first_time,
            "mag_new_min_gyr_sq": (s.mag_new_min_gyr * _DEG) ** 2, "mag_min_undisturbed_t": s.mag_min_undisturbed_time,
            "mag_max_rejection_t": s.mag_max_rejection_time, "mag_rejection_factor": s.mag_rejection_factor,
        }

    def reset(self):
        """Initial state: identity q_gyr, q_acc; δ = 0; b̂ = 0 with P = P₀ I; magnetic field
        taken as disturbed with no reference yet; every low-pass back in its averaging phase."""
        super().reset()
        st = self.state
        st[O_QGYR] = 1.0
        st[O_QACC] = 1.0
        p0 = self.params.bias_p0
        st[O_P] = st[O_P + 4] = st[O_P + 8] = p0
        st[O_MAG_DIST] = 1.0
        st[O_MAG_REJECT_T] = self.params.mag_max_rejection_t
        st[O_MAG_CAND_NORM] = -1.0
        st[O_K_MAG_INIT] = 1.0

    def set_quat(self, q):
        """Set the output orientation (sensor -> ENU) and mark the filter initialised. The
        almost-inertial frame, the low-passes, δ and the bias are kept; q_acc absorbs the change
        (q = [cos δ/2, 0, 0, sin δ/2] ⊗ q_acc ⊗ q_gyr; in 6D δ is not applied)."""
        super().set_quat(q)
        st = self.state
        qo = st[:4].copy()
        h = 0.5 * st[O_DELTA] if self.use_mag else 0.0
        qz_inv = np.array([math.cos(h), 0.0, 0.0, -math.sin(h)])
        qg_conj = st[O_QGYR:O_QGYR + 4] * np.array([1.0, -1.0, -1.0, -1.0])
        qa = _qmul(_qmul(qz_inv, qo), qg_conj)
        st[O_QACC:O_QACC + 4] = qa / np.linalg.norm(qa)


def _qmul(p, q):
    return np.array(multiply_scalar.py_func((p[0], p[1], p[2], p[3]), (q[0], q[1], q[2], q[3])))
