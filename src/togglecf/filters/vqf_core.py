"""VQF core: the orientation filter of Laidig & Seel, written from the paper's equations.

D. Laidig, T. Seel, "VQF: Highly accurate IMU orientation estimation with bias estimation and
magnetic disturbance rejection", Information Fusion 91:187-204, 2023 (arXiv 2203.17024).
Comments ``# Alg. 1 l. N`` cite the line of the paper's Algorithm 1 (basic VQF); the extensions
(rest detection, bias estimation, magnetic disturbance rejection) are cited by the paper's topic
and by the labelled equations (R1)…(M9) below, which spell out what the code computes.

Frames (ENU earth, quaternions sensor -> frame, ``[w, x, y, z]``, Hamilton):
ς sensor, I almost-inertial frame of pure strapdown integration, εᵢ 6D earth frame (heading
drifts), ε 9D earth frame. State: ``q_gyr`` (ς -> I), ``q_acc`` (I -> εᵢ), heading offset δ.

Per sample (gyro, then acc, then mag, as VQF; ``update_gyr``, ``update_acc``, ``update_bias``,
``update_mag``, ``update_output``, composed by ``core_update``, over the named state record
``CORE_STATE`` and the coefficients ``VQFCoreCoefficients``):

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
D = 1 + √2C + C², run in a "delta" form (``_lp_bank`` with the pair ``LowPass`` (4 b₀, a₂): level
and increment, the same transfer function as VQF's direct form II transposed, whose state would
kick the output when the learned filter changes τ_acc). To not depend on the first sample, each filter outputs the running mean of
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
from numba.cpython.unsafe.tuple import tuple_setitem

from togglecf.core.quaternion import from_rotvec_scalar, multiply_scalar, rotate_scalar
from togglecf.filters.base import (
    FilterSettings,
    OrientationFilter,
    dt_valid,
    gyro_valid,
    load_quat,
    record_of,
    record_view,
    state_record,
    store_quat,
    vector_ok,
)
from togglecf.filters.timeconst import gain_from_tau

__all__ = [
    "CORE_STATE",
    "CORE_STATE_FIELDS",
    "VQFCoreCoefficients",
    "CoreModulation",
    "LowPass",
    "core_update",
    "update_acc",
    "update_bias",
    "update_gyr",
    "update_mag",
    "update_output",
    "align_q_acc",
    "bias_noise_w",
    "core_coefficients",
    "reset_core_state",
    "VQFCoreFilter",
    "VQFCoreSettings",
    "butterworth_lp_coefficients",
    "lp_coefficients",
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


class LowPass(NamedTuple):
    """One LP₂ (module docstring) in the delta form of ``_lp_bank``, as the C keeps it
    (``tcf_vqf_lp_coef_t``): ``k`` = 4 b₀ = 1 + a₁ + a₂ and ``decay`` = a₂ (the C stores
    ``one_minus_decay`` = 1 − a₂ instead, for its float32 update; the Python keeps a₂ itself, the factor
    it multiplies by). Dimensionless."""

    k: float
    decay: float


class CoreModulation(NamedTuple):
    """The coefficients a learned filter may change from sample to sample (``filters.vqf_toggling``);
    the core itself runs them at their settings' values (``VQFCoreCoefficients.modulation``). Same
    units as in ``VQFCoreCoefficients``. The one place their order is written: records of it are
    built from ``_fields`` (``filters.base.record_fields``)."""

    acc_lp: LowPass  # the τ_acc low-pass (inclination, R̄ and (R b̂)‾ of the bias estimation)
    k_mag: float  # heading gain per sample, 1 − exp(−Ts/τ_mag)
    bias_w_motion: float  # W_motion of the bias estimation in motion [(rad/s)²]
    bias_w_vertical: float  # its vertical-axis counterpart
    rest_th_gyr_sq: float  # th_ω² [(rad/s)²]
    rest_th_acc_sq: float  # th_a² [(m/s²)²]


class VQFCoreCoefficients(NamedTuple):
    """Per-sample coefficients (from the settings and ``Ts``), passed to the kernel as ``params``.
    Angles and rates in rad, rad/s; covariances in (rad/s)²; flags 1.0/0.0."""

    use_mag: float
    max_dt: float
    ts: float  # nominal sampling time Ts [s]
    inv_ts: float  # 1/Ts [1/s]
    tau_acc: float
    modulation: CoreModulation  # at the settings' values (the core's own; a learned filter's fallback)
    tau_mag: float
    motion_bias: float
    rest_bias: float
    mag_rejection: float
    bias_p0: float
    bias_v: float
    bias_w_rest: float
    bias_clip: float
    rest_tau: float
    rest_lp: LowPass  # τ_rest low-pass (R1, R2)
    rest_min_t: float
    mag_cur_tau: float
    mag_lp: LowPass  # τ_mag,current low-pass of the field norm and dip (M1)
    k_mag_ref: float
    mag_norm_th: float
    mag_dip_th: float
    mag_new_time: float
    mag_new_first_time: float
    mag_new_min_gyr_sq: float  # ω_new,min² [(rad/s)²]
    mag_min_undisturbed_t: float
    mag_max_rejection_t: float
    mag_rejection_factor: float


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
def lp_coefficients(tau: float, ts: float) -> LowPass:
    """The ``LowPass`` pair of ``butterworth_lp_coefficients(tau, ts)``: (4 b₀, a₂)."""
    b0, _, _, _, a2 = butterworth_lp_coefficients(tau, ts)
    return LowPass(4.0 * b0, a2)


@njit(cache=True)
def bias_noise_w(sigma: float, v: float) -> float:
    """(B5): measurement noise W [(rad/s)²] whose steady-state posterior standard deviation is
    ``sigma`` [rad/s] with process noise ``v`` per sample: W = σ⁴/V + σ²."""
    s2 = sigma * sigma
    return s2 * s2 / v + s2


# ------------------------------------------------------------------------------------------
# State: a named record over the flat state (filters.base.state_record). A low-pass bank of
# C channels is a record (n, ready, s (C, 2)): s[c] = (level v, increment dv) of channel c;
# while averaging (ready = 0), n is the number of samples so far and s[c, 0] the running sum.
# ------------------------------------------------------------------------------------------

def _bank(name, channels):
    return [("n", f"{name}_n"), ("ready", f"{name}_ready"),
            ("s", tuple((f"{name}_{c}_s0", f"{name}_{c}_s1") for c in channels))]


def _named(name, suffixes, sep="_"):
    return name, tuple(f"{name}{sep}{s}" for s in suffixes)


_XYZ = ("x", "y", "z")
#: the core's state fields (``filters.base.state_record``); a learned filter's state starts with them
CORE_STATE_FIELDS = (
    _named("q_gyr", "wxyz"), _named("q_acc", "wxyz"), ("delta", "delta"), _named("bias", _XYZ),
    _named("bias_p", tuple(f"{i}{j}" for i in range(3) for j in range(3)), sep=""),
    ("rest_detected", "rest_detected"), ("rest_t", "rest_t"), _named("rest_gyr_lp", _XYZ),
    ("mag_dist_detected", "mag_dist_detected"), ("mag_ref_norm", "mag_ref_norm"), ("mag_ref_dip", "mag_ref_dip"),
    ("mag_undisturbed_t", "mag_undisturbed_t"), ("mag_reject_t", "mag_reject_t"),
    ("mag_cand_norm", "mag_cand_norm"), ("mag_cand_dip", "mag_cand_dip"), ("mag_cand_t", "mag_cand_t"),
    ("k_mag_init", "k_mag_init"),
    ("acc_lp", _bank("acc_lp", _XYZ)),
    ("rest_gyr_bank", _bank("rest_gyr_bank", _XYZ)),
    ("rest_acc_bank", _bank("rest_acc_bank", _XYZ)),
    ("bias_r_lp", _bank("bias_r_lp", tuple(f"r{i}{j}" for i in range(3) for j in range(3)))),
    ("bias_rb_lp", _bank("bias_rb_lp", ("x", "y"))),
    ("mag_nd_lp", _bank("mag_nd_lp", ("norm", "dip"))),
)
CORE_STATE, _STATE_NAMES = state_record(CORE_STATE_FIELDS)
_core_state = record_view(CORE_STATE)

_DIAG_NAMES = ("rest", "mag_dist", "bias_x", "bias_y", "bias_z", "bias_sigma", "delta", "k_mag")


# ------------------------------------------------------------------------------------------
# Kernel building blocks
# ------------------------------------------------------------------------------------------

@njit(cache=True, inline="always")
def _lp_bank(bank, xs, c, tau, ts):
    """One sample of the low-pass bank ``bank`` (a state record, module docstring) with
    coefficients ``c`` (a ``LowPass``): the outputs for the inputs ``xs`` (a tuple, one per
    channel). Per channel (v, dv) = ``bank.s[ch]``, the second-order LP
    H(z) = b0 (1 + z⁻¹)² / (1 + a1 z⁻¹ + a2 z⁻²) with unit DC gain.

    Delta form (as the C core, ``embedded/tcf_vqf.c``): with K = 4 b0 = 1 + a1 + a2 and
    β = 1 − a2, v the level and dv its last increment,
        dv_k = (1 − β) dv_{k−1} + K (x_k − v_{k−1}),   v_k = v_{k−1} + dv_k,
        y_k  = v_{k−1} + (dv_k − dv_{k−1}) / 4.
    The same transfer function as VQF's direct form II transposed, but its state is the
    signal itself (level and increment), not a coefficient-dependent mix: when the learned
    filter changes τ_acc between samples (``filters.vqf_toggling``) the output continues
    smoothly, where the DF2T state run on with new coefficients kicks the output.

    For its first τ [s] the bank averages (outputs the running mean); then every channel starts
    in the steady state of its mean (v = mean, dv = 0)."""
    s = bank.s
    ys = xs
    if bank.ready > 0.5:
        decay, k = c.decay, c.k  # read once: c may be a record in the same memory as s
        for ch in range(len(xs)):
            dv = decay * s[ch, 1] + k * (xs[ch] - s[ch, 0])  # (1 − β) = a2
            ys = tuple_setitem(ys, ch, s[ch, 0] + 0.25 * (dv - s[ch, 1]))
            s[ch, 0] += dv
            s[ch, 1] = dv
        return ys
    n = bank.n + 1.0
    bank.n = n
    for ch in range(len(xs)):  # averaging phase: running sum, output the mean
        s[ch, 0] += xs[ch]
        ys = tuple_setitem(ys, ch, s[ch, 0] / n)
    if n * ts >= tau:
        for ch in range(len(xs)):
            s[ch, 0] = s[ch, 0] / n
            s[ch, 1] = 0.0
        bank.ready = 1.0
    return ys


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
def _bias_correct(st, p, ex, ey, ez, pmt, s):
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
    b = st.bias
    b[0] += k[0] * e0 + k[1] * e1 + k[2] * e2
    b[1] += k[3] * e0 + k[4] * e1 + k[5] * e2
    b[2] += k[6] * e0 + k[7] * e1 + k[8] * e2
    kmp = _mmt(k, pmt)  # K (P Mᵀ)ᵀ = K M P
    for i in range(9):
        st.bias_p[i] -= kmp[i]


# ------------------------------------------------------------------------------------------
# The step, split as VQF's updateGyr / updateAcc / updateMag. Each part takes the state record
# ``st`` (``CORE_STATE``, or a record that starts with its fields), the coefficients ``p``
# (``VQFCoreCoefficients``) and ``mod`` (a ``CoreModulation``, or a record with its fields).
# ------------------------------------------------------------------------------------------

@njit(cache=True, inline="always")
def update_gyr(st, p, mod, gyr, dt):
    """A valid gyro sample ω [rad/s] over Δt [s]: rest detection (R1), then Alg. 1 l. 8."""
    if p.rest_bias > 0.5 or p.mag_rejection > 0.5:  # (R1); the rest low-pass also feeds (M3)
        g0, g1, g2 = _lp_bank(st.rest_gyr_bank, (gyr[0], gyr[1], gyr[2]), p.rest_lp, p.rest_tau, p.ts)
        st.rest_gyr_lp[0], st.rest_gyr_lp[1], st.rest_gyr_lp[2] = g0, g1, g2
        d0, d1, d2 = gyr[0] - g0, gyr[1] - g1, gyr[2] - g2
        if (d0 * d0 + d1 * d1 + d2 * d2 >= mod.rest_th_gyr_sq or abs(g0) > p.bias_clip
                or abs(g1) > p.bias_clip or abs(g2) > p.bias_clip):
            st.rest_t = 0.0
            st.rest_detected = 0.0
        else:
            st.rest_t += p.ts
            if st.rest_t >= p.rest_min_t:
                st.rest_detected = 1.0
    # Alg. 1 l. 8: strapdown integration of the bias-corrected rate over the actual Δt
    b = st.bias
    dq = from_rotvec_scalar((gyr[0] - b[0]) * dt, (gyr[1] - b[1]) * dt, (gyr[2] - b[2]) * dt)
    store_quat(st.q_gyr, _unit(multiply_scalar(load_quat(st.q_gyr), dq)))


@njit(cache=True, inline="always")
def update_acc(st, p, mod, acc):
    """A valid accelerometer sample a [m/s²]: rest detection (R2), then the inclination correction
    (Alg. 1 l. 9-14). Returns ``(corrected, a_x, a_y)``: whether q_acc was corrected, and the
    normalised low-passed acceleration in εᵢ (l. 12) that the bias estimation (B3) uses."""
    if p.rest_bias > 0.5:  # (R2)
        l0, l1, l2 = _lp_bank(st.rest_acc_bank, (acc[0], acc[1], acc[2]), p.rest_lp, p.rest_tau, p.ts)
        d0, d1, d2 = acc[0] - l0, acc[1] - l1, acc[2] - l2
        if d0 * d0 + d1 * d1 + d2 * d2 >= mod.rest_th_acc_sq:
            st.rest_t = 0.0
            st.rest_detected = 0.0
    ai = rotate_scalar(load_quat(st.q_gyr), (acc[0], acc[1], acc[2]))  # Alg. 1 l. 9
    f = _lp_bank(st.acc_lp, ai, mod.acc_lp, p.tau_acc, p.ts)  # Alg. 1 l. 10
    qa = load_quat(st.q_acc)
    ae = rotate_scalar(qa, f)  # Alg. 1 l. 11
    na = math.sqrt(ae[0] * ae[0] + ae[1] * ae[1] + ae[2] * ae[2])
    if not (na > 0.0 and na < math.inf):
        return False, 0.0, 0.0
    rn = 1.0 / na
    ax, ay, az = ae[0] * rn, ae[1] * rn, ae[2] * rn  # Alg. 1 l. 12
    qw = math.sqrt(max(0.5 * (az + 1.0), 0.0))  # Alg. 1 l. 13
    if qw > 1e-6:  # Alg. 1 l. 14
        h = 0.5 / qw
        corr = (qw, ay * h, -ax * h, 0.0)
    else:  # a points down: the 180° correction about any horizontal axis
        corr = (0.0, 1.0, 0.0, 0.0)
    store_quat(st.q_acc, _unit(multiply_scalar(corr, qa)))
    st.initialized = 1.0
    return True, ax, ay


@njit(cache=True, inline="always")
def update_bias(st, p, mod, ax, ay):
    """Gyro bias estimation (B1)-(B5) after an inclination correction with the normalised
    low-passed acceleration (a_x, a_y) in εᵢ. Returns q_6D (Alg. 1 l. 15)."""
    b0, b1, b2 = st.bias[0], st.bias[1], st.bias[2]
    q6 = multiply_scalar(load_quat(st.q_acc), load_quat(st.q_gyr))  # Alg. 1 l. 15
    r = _matrix(q6)  # R(q_6D)
    rb = (r[0] * b0 + r[1] * b1 + r[2] * b2, r[3] * b0 + r[4] * b1 + r[5] * b2)
    rl = _lp_bank(st.bias_r_lp, r, mod.acc_lp, p.tau_acc, p.ts)  # R̄ = LP₂(R; τ_acc)
    rb0, rb1 = _lp_bank(st.bias_rb_lp, rb, mod.acc_lp, p.tau_acc, p.ts)  # (R b̂)‾ = LP₂(R b̂; τ_acc), x and y
    pd = st.bias_p
    for i in range(3):  # (B1): P_ii ← P_ii + V while P_ii < P₀ (also without a measurement)
        if pd[4 * i] < p.bias_p0:
            pd[4 * i] += p.bias_v
    P = (pd[0], pd[1], pd[2], pd[3], pd[4], pd[5], pd[6], pd[7], pd[8])
    if p.rest_bias > 0.5 and st.rest_detected > 0.5:  # (B2): y = ω̄, M = I, P Mᵀ = P
        w = p.bias_w_rest
        g = st.rest_gyr_lp
        _bias_correct(st, p, g[0] - b0, g[1] - b1, g[2] - b2, P,
                      (P[0] + w, P[1], P[2], P[3], P[4] + w, P[5], P[6], P[7], P[8] + w))
    elif p.motion_bias > 0.5:  # (B3): M = R̄
        ex = -ay * p.inv_ts + rb0 - (rl[0] * b0 + rl[1] * b1 + rl[2] * b2)
        ey = ax * p.inv_ts + rb1 - (rl[3] * b0 + rl[4] * b1 + rl[5] * b2)
        ez = -(rl[6] * b0 + rl[7] * b1 + rl[8] * b2)
        pmt = _mmt(P, rl)  # P Mᵀ
        s = _mm(rl, pmt)  # M P Mᵀ
        _bias_correct(st, p, ex, ey, ez, pmt, (s[0] + mod.bias_w_motion, s[1], s[2], s[3], s[4] + mod.bias_w_motion,
                                               s[5], s[6], s[7], s[8] + mod.bias_w_vertical))
    for i in range(3):
        st.bias[i] = _clip(st.bias[i], p.bias_clip)
    return q6


@njit(cache=True, inline="always")
def _mag_disturbance(st, p, me):
    """Magnetic disturbance detection (M1)-(M3) from the field in εᵢ, ``me``."""
    nrm = math.sqrt(me[0] * me[0] + me[1] * me[1] + me[2] * me[2])  # (M1)
    dip = -math.asin(min(max(me[2] / nrm, -1.0), 1.0))
    if p.mag_cur_tau > 0.0:
        nrm, dip = _lp_bank(st.mag_nd_lp, (nrm, dip), p.mag_lp, p.mag_cur_tau, p.ts)
    ref_n = st.mag_ref_norm  # (M2)
    if abs(nrm - ref_n) < p.mag_norm_th * ref_n and abs(dip - st.mag_ref_dip) < p.mag_dip_th:
        st.mag_undisturbed_t += p.ts
        if st.mag_undisturbed_t >= p.mag_min_undisturbed_t:
            st.mag_dist_detected = 0.0
            st.mag_ref_norm += p.k_mag_ref * (nrm - ref_n)
            st.mag_ref_dip += p.k_mag_ref * (dip - st.mag_ref_dip)
    else:
        st.mag_undisturbed_t = 0.0
        st.mag_dist_detected = 1.0
    cand_n = st.mag_cand_norm  # (M3)
    if abs(nrm - cand_n) < p.mag_norm_th * cand_n and abs(dip - st.mag_cand_dip) < p.mag_dip_th:
        g = st.rest_gyr_lp
        if g[0] * g[0] + g[1] * g[1] + g[2] * g[2] >= p.mag_new_min_gyr_sq:  # ‖ω̄‖ ≥ ω_new,min
            st.mag_cand_t += p.ts
        st.mag_cand_norm += p.k_mag_ref * (nrm - cand_n)
        st.mag_cand_dip += p.k_mag_ref * (dip - st.mag_cand_dip)
        if st.mag_dist_detected > 0.5 and (st.mag_cand_t >= p.mag_new_time or (
                st.mag_ref_norm == 0.0 and st.mag_cand_t >= p.mag_new_first_time)):
            st.mag_ref_norm = st.mag_cand_norm
            st.mag_ref_dip = st.mag_cand_dip
            st.mag_dist_detected = 0.0
            st.mag_undisturbed_t = p.mag_min_undisturbed_t
    else:
        st.mag_cand_t = 0.0
        st.mag_cand_norm = nrm
        st.mag_cand_dip = dip


@njit(cache=True, inline="always")
def update_mag(st, p, mod, mag, q6):
    """A valid magnetometer sample (9D) with the current q_6D: disturbance detection (M1)-(M3),
    then the heading correction (Alg. 1 l. 17-19, M4, M5). Returns the gain k used."""
    me = rotate_scalar(q6, (mag[0], mag[1], mag[2]))  # Alg. 1 l. 17
    if p.mag_rejection > 0.5:
        _mag_disturbance(st, p, me)
    dis = _wrap(math.atan2(me[0], me[1]) - st.delta)  # Alg. 1 l. 18-19
    k = mod.k_mag
    if p.mag_rejection > 0.5:  # (M4)
        if st.mag_dist_detected > 0.5:
            if st.mag_reject_t <= p.mag_max_rejection_t:
                st.mag_reject_t += p.ts
                k = 0.0
            else:
                k = k / p.mag_rejection_factor
        else:
            st.mag_reject_t = max(st.mag_reject_t - p.mag_rejection_factor * p.ts, 0.0)
    kinit = st.k_mag_init  # (M5): k ≥ 1/N for the N-th sample while 1/N·τ_mag ≥ Ts
    if kinit != 0.0:
        k = max(k, kinit)
        kinit = kinit / (kinit + 1.0)
        st.k_mag_init = 0.0 if kinit * p.tau_mag < p.ts else kinit
    st.delta = _wrap(st.delta + k * dis)  # Alg. 1 l. 19
    return k


@njit(cache=True, inline="always")
def update_output(st, p, q6, k, diag):
    """The output orientation (Alg. 1 l. 21 in 9D, q_6D in 6D) and the diagnostics, with k the
    heading gain of this sample."""
    if p.use_mag > 0.5:  # Alg. 1 l. 21: q_9D = [cos δ/2, 0, 0, sin δ/2] ⊗ q_6D
        h = 0.5 * st.delta
        c, s = math.cos(h), math.sin(h)
        q = (c * q6[0] - s * q6[3], c * q6[1] - s * q6[2], c * q6[2] + s * q6[1], c * q6[3] + s * q6[0])
    else:
        q = q6
    store_quat(st.quat, q)
    diag[0] = st.rest_detected
    diag[1] = st.mag_dist_detected if p.use_mag > 0.5 else 0.0
    diag[2] = st.bias[0]
    diag[3] = st.bias[1]
    diag[4] = st.bias[2]
    diag[5] = math.sqrt(max(st.bias_p[0], st.bias_p[4], st.bias_p[8]))
    diag[6] = st.delta
    diag[7] = k


@njit(cache=True, inline="always")
def core_update(st, p, mod, gyr, acc, mag, dt, diag):
    """One sample of the VQF core (module docstring) on the state record ``st`` with coefficients
    ``p`` and the modulated ones ``mod``. Bad samples (policy of ``filters.base``): an invalid
    gyro sample or Δt skips ``update_gyr``, an invalid accelerometer sample ``update_acc`` and
    ``update_bias``, an invalid magnetometer sample ``update_mag``. diag: see
    ``VQFCoreFilter.diagnostic_names``."""
    if gyro_valid(gyr) and dt_valid(dt, p.max_dt):
        update_gyr(st, p, mod, gyr, dt)
    have_q6 = False  # q_6D is computed once per sample, in the bias estimation when it runs
    q6 = (1.0, 0.0, 0.0, 0.0)
    if vector_ok(acc):
        corrected, ax, ay = update_acc(st, p, mod, acc)
        if corrected and (p.rest_bias > 0.5 or p.motion_bias > 0.5):
            q6 = update_bias(st, p, mod, ax, ay)
            have_q6 = True
    if not have_q6:
        q6 = multiply_scalar(load_quat(st.q_acc), load_quat(st.q_gyr))  # Alg. 1 l. 15
    k = 0.0
    if p.use_mag > 0.5 and vector_ok(mag):
        k = update_mag(st, p, mod, mag, q6)
    update_output(st, p, q6, k, diag)


@njit(cache=True)
def vqf_core_step(state, params, gyr, acc, mag, dt, diag):
    """One sample of the VQF core (module docstring) on the flat ``state`` (read as the record
    ``CORE_STATE``). diag: see ``VQFCoreFilter.diagnostic_names``."""
    core_update(_core_state(state), params, params.modulation, gyr, acc, mag, dt, diag)


def core_coefficients(s: VQFCoreSettings, ts: float) -> dict:
    """The core's ``VQFCoreCoefficients`` fields (all but ``use_mag``, ``max_dt``) by name, from the
    settings ``s`` (VQF's units) and the sampling time ``ts`` [s]; rates in rad/s."""
    # (B5): variances in (rad/s)²
    p_motion = (s.bias_sigma_motion * _DEG) ** 2
    p_rest = (s.bias_sigma_rest * _DEG) ** 2
    v = (_BIAS_DRIFT_DEG_S * _DEG) ** 2 * ts / s.bias_forgetting_time
    w_motion = p_motion * p_motion / v + p_motion
    modulation = CoreModulation(
        acc_lp=lp_coefficients(s.tau_acc, ts), k_mag=gain_from_tau(s.tau_mag, ts), bias_w_motion=w_motion,
        bias_w_vertical=w_motion / max(s.bias_vertical_forgetting_factor, 1e-10),
        rest_th_gyr_sq=(s.rest_th_gyr * _DEG) ** 2, rest_th_acc_sq=s.rest_th_acc ** 2)
    return {
        "ts": ts, "inv_ts": 1.0 / ts, "tau_acc": s.tau_acc, "modulation": modulation, "tau_mag": s.tau_mag,
        "motion_bias": float(s.motion_bias_est_enabled), "rest_bias": float(s.rest_bias_est_enabled),
        "mag_rejection": float(s.mag_dist_rejection_enabled),
        "bias_p0": (s.bias_sigma_init * _DEG) ** 2, "bias_v": v,
        "bias_w_rest": p_rest * p_rest / v + p_rest, "bias_clip": s.bias_clip * _DEG,
        "rest_tau": s.rest_filter_tau, "rest_lp": lp_coefficients(s.rest_filter_tau, ts),
        "rest_min_t": s.rest_min_t, "mag_cur_tau": s.mag_current_tau,
        "mag_lp": lp_coefficients(s.mag_current_tau, ts) if s.mag_current_tau > 0 else LowPass(4.0, 0.0),
        "k_mag_ref": gain_from_tau(s.mag_ref_tau, ts), "mag_norm_th": s.mag_norm_th,
        "mag_dip_th": s.mag_dip_th * _DEG, "mag_new_time": s.mag_new_time, "mag_new_first_time": s.mag_new_first_time,
        "mag_new_min_gyr_sq": (s.mag_new_min_gyr * _DEG) ** 2, "mag_min_undisturbed_t": s.mag_min_undisturbed_time,
        "mag_max_rejection_t": s.mag_max_rejection_time, "mag_rejection_factor": s.mag_rejection_factor,
    }


def reset_core_state(st, params):
    """The core's initial state in the record ``st`` (all zeros before; ``CORE_STATE``, or a record
    that starts with its fields) for the coefficients ``params``: identity q_gyr, q_acc; δ = 0; b̂ = 0
    with P = P₀ I; magnetic field taken as disturbed with no reference yet; every low-pass back in its
    averaging phase."""
    st.q_gyr[0] = 1.0
    st.q_acc[0] = 1.0
    p0 = params.bias_p0
    st.bias_p[0] = st.bias_p[4] = st.bias_p[8] = p0
    st.mag_dist_detected = 1.0
    st.mag_reject_t = params.mag_max_rejection_t
    st.mag_cand_norm = -1.0
    st.k_mag_init = 1.0


def align_q_acc(st, use_mag: bool):
    """After the output orientation ``st.quat`` was set: q_acc such that q = [cos δ/2, 0, 0, sin δ/2]
    ⊗ q_acc ⊗ q_gyr (in 6D, δ not applied); the almost-inertial frame, the low-passes, δ and the bias
    are kept."""
    qo = st.quat.copy()
    h = 0.5 * st.delta if use_mag else 0.0
    qz_inv = np.array([math.cos(h), 0.0, 0.0, -math.sin(h)])
    qg_conj = st.q_gyr * np.array([1.0, -1.0, -1.0, -1.0])
    qa = _qmul(_qmul(qz_inv, qo), qg_conj)
    st.q_acc[:] = qa / np.linalg.norm(qa)


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
    #: the numpy structured dtype of the whole flat state (``filters.base.state_record``)
    state_dtype = CORE_STATE
    diagnostic_names = _DIAG_NAMES
    step = vqf_core_step

    def _coefficients(self) -> dict:
        return core_coefficients(self.settings, self.Ts)

    @property
    def record(self):
        """The state as a named record (``CORE_STATE``): a view, writes go to ``state``."""
        return record_of(self.state, self.state_dtype)

    def reset(self):
        """Initial state (``reset_core_state``)."""
        super().reset()
        reset_core_state(self.record, self.params)

    def set_quat(self, q):
        """Set the output orientation (sensor -> ENU) and mark the filter initialised; q_acc absorbs
        the change (``align_q_acc``)."""
        super().set_quat(q)
        align_q_acc(self.record, self.use_mag)


def _qmul(p, q):
    return np.array(multiply_scalar.py_func((p[0], p[1], p[2], p[3]), (q[0], q[1], q[2], q[3])))
