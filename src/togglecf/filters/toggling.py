"""Toggling-gain complementary filter: gains switched by a predicted motion state.

Per sample k, with predictions ``pred = [p_1..p_S, η̂_a(3), η̂_m(3)]`` (class probabilities
of the motion state and the predicted acc/mag noise in the sensor frame):

1. gyro bias at rest        b ← b + k_b · p_static · (ω − b)      when |ω − b| < ω_gate
2. gyro propagation         Δq = exp((ω − b) Δt / 2),  q_g = q ⊗ Δq
   the predicted vectors follow the sensor: v ← Δq* ⊗ v ⊗ Δq   (R_gᵀ v: earth-fixed
   directions rotate opposite to the body)
3. noise removal            a_d = a − w_a η̂_a,  m_d = m − w_m η̂_m   (w learned in [0, 1]: a
   regressor that does not generalise to a disturbance can be switched down)
4. gain toggling            α_a = Σ_s p_s α_a[s],  α_m = Σ_s p_s α_m[s]   (α a function of
   the class probabilities; a hard toggle when the probabilities are one-hot); the
   magnetometer gain also falls with the predicted disturbance: α_m / (1 + min((|η̂_m| / σ_m)², f_reject − 1)),
   bounded by the rejection factor f_reject (as the VQF core's rejection and the learned VQF's back-off: the
   heading gain is never below α_m / f_reject, so a disturbance predicted on a sensor the models never saw
   slows the heading correction by at most that factor instead of switching it off)
   **Fallback**: with no prediction (NaN probabilities: before the first full window,
   or a window outside the models' training range, ``learn.ranges``) or a prediction whose
   confidence c = max_s p_s / Σ_s p_s is below ``confidence_floor`` c₀, the models are not
   used: α_a, α_m are the *cautious* gains, per sensor the slowest of the per-state ones (trust
   the gyro where the motion is unknown), no noise is removed (step 3) and the bias does not
   move at rest (step 1; step 5b, part of the core, still runs). With every sample falling back, the filter is the same filter with every
   state at those slowest time constants and the learned terms off (test). A hard switch, like
   the toggling itself; c₀ = 0 never falls back on a valid prediction. (The rule, and how it
   differs from the learned VQF's blend towards its core, is in ``filters.prediction``.) Cautious rather than the
   fixed CF's τ: the out-of-fold predictions the gains are learned on fall back mostly on
   disturbed windows, where a fast correction follows the disturbance (docs/concepts/
   toggling-filter.md gives the measurement).
5. vector CF step           a_pred ← (1 − α_a) a_pred + α_a a_d; the field **follows** (9D): m_pred ← R m_pred
   with R the shortest-arc rotation from the old a_pred's direction to the new one (``turn_as``), since
   a tilt correction turns the estimated frame, not the gravity direction alone (as VQF's and Mahony's
   corrections rotate the orientation). Without it a tilt correction changes the angle between a_pred
   and m_pred, and step 6's heading (m_pred's horizontal part) by up to tan(dip) times the tilt step:
   the accelerometer's disturbances in fast motion leak into the heading. Then m_pred ← (1 − α_m)
   m_pred + α_m m_d, with α_m lowered where needed so that the step turns m_pred by at most ω_m Ts
   (``mag_rate_limit`` ω_m [rad/s]; 0: no bound): the heading correction moves at most ω_m, however
   large the error, as Madgwick's normalised gradient step moves at most β. A disturbance of the field then turns the
   heading by at most ω_m times its duration, while small errors still decay with τ_mag
5b. heading bias in motion (9D)  b ← b + (sin θ_h / τ_i) û, with θ_h the angle by which the heading correction
   just turned m_pred's horizontal part about the estimated vertical û = a_pred / |a_pred|: the
   integral term of a PI heading loop (as Mahony's k_I, on the heading only). Step 1 learns the bias only
   at predicted rest, and a bias left in motion (about 1 °/s on a consumer gyroscope) against the
   linear heading correction holds the heading behind by bias × τ_mag (10° at 0.6 °/s and τ_mag
   17.5 s). Fed only where the heading correction is evidence of the bias: the field passes VQF's
   magnetic disturbance check (its norm within ``mag_norm_threshold`` of the reference norm and its
   dip, asin(−m̂ · û), within ``mag_dip_threshold`` of the reference dip; the reference follows the
   accepted field with ``mag_ref_tau`` from the first magnetometer sample, as VQF's magRefTau; a new
   field is never adopted, so a field that stays disturbed stops the feed) and the accelerometer
   reads gravity alone (||a_d| − g| < ``acc_norm_threshold`` g: the vertical û the heading is measured
   about is then trustworthy). The feed never takes |b| above ``heading_bias_clip`` (VQF's biasClip,
   2 °/s): a wrong feed costs at most that rate. The loop's damping is ζ = ½ √(τ_i / τ_mag).
6. acc/mag orientation      q_am = from_acc_mag(a_pred, m_pred)   (6D: q_g tilted onto a_pred)
7. output blend             q = normalize((1 − γ) q_g + γ q_am)    (LERP on the short arc)

Gains: every per-sample gain above (α_a[s], α_m[s], k_b, γ) is set as a time constant [s] in
``TogglingSettings`` (``tau_acc``, ``tau_mag``, ``bias_tau``, ``output_tau``) and converted once
from the filter's nominal ``Ts`` as k = 1 − exp(−Ts/τ) (``filters.timeconst``; τ = 0: k = 1,
τ < 0: k = 0). The kernel gets the per-sample values through ``TogglingCoefficients``. The
coefficients use the nominal ``Ts``, not each sample's Δt (as VQF does).

Why this geometric form: blending the *vectors* (step 5) gives tilt and heading their own
gains (``from_acc_mag`` takes tilt from a_pred only and heading from m_pred's horizontal
part), and the LERP of step 7 is the quaternion equivalent of projecting
``(1 − γ) R_g + γ R_am`` back onto a rotation (both agree to first order in the angle
between them; LERP stays exactly unit-norm after normalising). γ = 1 makes the orientation
a pure function of the two gyro-propagated vectors; γ < 1 adds a second smoothing stage.

Bad samples follow the policy of ``filters.base`` (non-finite or saturated gyro, bad Δt: no propagation;
bad acc: no tilt update; bad mag: no heading update). Non-finite predictions count as
"no prediction": the fallback of step 4 (the cautious gains, η̂ = 0).
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
from numba import njit

from togglecf.core.quaternion import multiply_scalar, normalize_scalar, rotate_inverse_scalar
from togglecf.data.broad import GRAVITY
from togglecf.filters.base import (
    FilterSettings,
    acc_mag_quaternion,
    field_agrees,
    gyro_increment,
    gyro_valid,
    load_quat,
    store_quat,
    vector_ok,
)
from togglecf.filters.prediction import (
    LEARNED,
    LOW_CONFIDENCE,
    PredictionDrivenFilter,
    PredictionLayout,
    back_off,
    class_evidence,
    predicted_disturbance,
    remove_noise,
    switch_status,
)
from togglecf.filters.timeconst import gain

__all__ = [
    "TogglingCoefficients",
    "TogglingFilter",
    "TogglingSettings",
    "heading_bias_step",
    "rate_bounded_gain",
    "toggle_step",
    "turn_as",
]

_STATE = ("bias_x", "bias_y", "bias_z", "a_pred_x", "a_pred_y", "a_pred_z", "m_pred_x", "m_pred_y", "m_pred_z",
          "mag_ref_norm", "mag_ref_dip")


@dataclass(frozen=True)
class TogglingSettings(FilterSettings):
    """Attributes:
        states: motion-state names, in the order of the classifier's classes.
        tau_acc: per-state time constant [s] of the denoised accelerometer's vector CF (step 5):
            α_a[s] = 1 − exp(−Ts/τ) (0: α = 1; < 0: α = 0, no tilt correction in that state).
        tau_mag: per-state time constant [s] of the denoised magnetometer's, likewise.
        output_tau: time constant [s] of the output blend (step 7), γ = 1 − exp(−Ts/τ);
            0 (default): γ = 1, the orientation from the vectors only. Must be >= 0.
        static_state: name of the state in which the gyro bias is learned.
        bias_tau: time constant [s] of the bias low-pass at p_static = 1 (k_b = 1 − exp(−Ts/τ);
            < 0 disables the bias estimate).
        bias_gate: largest |ω − b| [rad/s] still taken as bias (rejects slow motion at "rest").
        mag_disturbance_scale: σ_m [µT] of step 4; 0 turns the disturbance scaling off.
        mag_rejection_factor: f_reject ≥ 1 (dimensionless) of step 4: the largest divisor of the
            magnetometer gain by the back-off (the heading gain stays at least α_m / f_reject); the
            default 2 is the VQF core's rejection factor; 1 turns the back-off off. Finite (the
            C export writes it as a float32 constant).
        noise_weight_acc, noise_weight_mag: w_a, w_m of step 3, in [0, 1].
        confidence_floor: c₀ in [0, 1) of step 4's fallback: a prediction whose top class
            probability (of their sum) is below it is not used; 0 (default): every valid one is.
        mag_rate_limit: ω_m [rad/s] of step 5: the fastest the magnetometer's vector CF step may turn
            m_pred (so the heading); 0 (default): no bound. Finite and >= 0.
        heading_bias_tau: τ_i [s] of step 5b, the heading bias's integral time; 0: off (no bias learned
            in motion). Default 30 s (ζ ≈ 0.65 at τ_mag 17.5 s; chosen after looking at the developer
            datasets left out, docs/concepts/toggling-filter.md).
        heading_bias_clip: largest |b| [rad/s] step 5b may reach (VQF's biasClip: 2 °/s).
        mag_norm_threshold: largest relative deviation of |m| from the reference norm for step 5b's
            field check (VQF's magNormTh: 0.1).
        mag_dip_threshold: largest deviation [rad] of the dip from the reference dip (VQF's magDipTh: 10°).
        mag_ref_tau: time constant [s] with which the reference norm and dip follow the accepted field
            (VQF's magRefTau: 20 s).
        acc_norm_threshold: largest relative deviation of |a| from g [m/s², ``data.broad.GRAVITY``] at
            which step 5b trusts the vertical (0.1).
    The defaults are placeholders for a two-state model; ``togglecf train`` learns the gains
    on the training trials and stores them with the models (``gains.json``, format 2). They are
    per-sample gains at BROAD's 285.714 Hz as time constants, τ = −Ts/ln(1 − α) rounded to 4
    digits: α_acc (0.01, 0.0005) -> (0.3482, 6.998) s, α_mag (0.002, 0.0005) -> (1.748, 6.998) s,
    bias gain 0.002 -> 1.748 s, γ = 1 -> 0 s.
    """

    states: tuple = ("static", "dynamic")
    tau_acc: tuple = (0.3482, 6.998)
    tau_mag: tuple = (1.748, 6.998)
    output_tau: float = 0.0
    static_state: str = "static"
    bias_tau: float = 1.748
    bias_gate: float = 0.05
    mag_disturbance_scale: float = 0.0
    mag_rejection_factor: float = 2.0
    noise_weight_acc: float = 1.0
    noise_weight_mag: float = 1.0
    confidence_floor: float = 0.0
    mag_rate_limit: float = 0.0
    heading_bias_tau: float = 30.0
    heading_bias_clip: float = math.radians(2.0)
    mag_norm_threshold: float = 0.1
    mag_dip_threshold: float = math.radians(10.0)
    mag_ref_tau: float = 20.0
    acc_norm_threshold: float = 0.1

    def __post_init__(self):
        super().__post_init__()
        n = len(self.states)
        object.__setattr__(self, "states", tuple(self.states))
        object.__setattr__(self, "tau_acc", tuple(float(a) for a in self.tau_acc))
        object.__setattr__(self, "tau_mag", tuple(float(a) for a in self.tau_mag))
        if n < 1 or len(self.tau_acc) != n or len(self.tau_mag) != n:
            raise ValueError(f"tau_acc and tau_mag need one time constant per state {self.states}")
        for name in ("tau_acc", "tau_mag"):
            if not all(math.isfinite(a) for a in getattr(self, name)):
                raise ValueError(f"{name} must be finite time constants [s], got {getattr(self, name)}")
        if not self.output_tau >= 0.0:
            raise ValueError(f"output_tau must be >= 0 s, got {self.output_tau}")
        if self.static_state not in self.states:
            raise ValueError(f"static_state {self.static_state!r} is not one of {self.states}")
        if not (0.0 <= self.noise_weight_acc <= 1.0 and 0.0 <= self.noise_weight_mag <= 1.0):
            raise ValueError("noise weights must be in [0, 1]")
        if self.mag_disturbance_scale < 0.0:
            raise ValueError(f"mag_disturbance_scale must be >= 0 µT, got {self.mag_disturbance_scale}")
        if not 1.0 <= self.mag_rejection_factor < math.inf:
            raise ValueError(f"mag_rejection_factor must be finite and >= 1, got {self.mag_rejection_factor}")
        if not self.bias_gate >= 0.0:
            raise ValueError(f"bias_gate must be >= 0 rad/s, got {self.bias_gate}")
        if not 0.0 <= self.confidence_floor < 1.0:
            raise ValueError(f"confidence_floor must be in [0, 1), got {self.confidence_floor}")
        if not 0.0 <= self.mag_rate_limit < math.inf:
            raise ValueError(f"mag_rate_limit must be finite and >= 0 rad/s, got {self.mag_rate_limit}")
        for name, unit in (("heading_bias_tau", "s"), ("heading_bias_clip", "rad/s"), ("mag_norm_threshold", ""),
                           ("mag_dip_threshold", "rad"), ("mag_ref_tau", "s"), ("acc_norm_threshold", "")):
            if not 0.0 <= getattr(self, name) < math.inf:
                raise ValueError(f"{name} must be finite and >= 0 {unit}".rstrip() + f", got {getattr(self, name)}")


class TogglingCoefficients(NamedTuple):
    """``params`` of ``toggle_step``: the common ``use_mag``, ``max_dt`` (see ``filters.base``), then

    Attributes:
        layout: the prediction row's layout for S = ``len(TogglingSettings.states)`` motion states
            (``filters.prediction.PredictionLayout``).
        alpha_acc, alpha_mag: per-state gains per sample, float64 arrays ``(S,)``, from
            ``TogglingSettings.tau_acc``/``tau_mag`` and ``Ts`` (module docstring, "Gains").
        gamma: output blend weight per sample, from ``output_tau``.
        bias_gain: bias low-pass gain per sample at p_static = 1, from ``bias_tau``.
        static_index: index of ``static_state`` in ``states`` (its probability drives the bias).
        bias_gate, mag_disturbance_scale, noise_weight_acc, noise_weight_mag, confidence_floor:
            the ``TogglingSettings`` of the same names.
        mag_rejection_factor: f_reject of step 4 (``TogglingSettings.mag_rejection_factor``).
        alpha_fallback_acc, alpha_fallback_mag: the cautious gains per sample of step 4's
            fallback: the smallest of ``alpha_acc``/``alpha_mag``.
        tan_mag_step: tan(ω_m Ts), the largest turn of m_pred per sample of step 5
            (``TogglingSettings.mag_rate_limit``; 0: no bound).
        heading_bias_rate: 1 / τ_i [1/s] of step 5b (0: off).
        heading_bias_clip, mag_norm_threshold, mag_dip_threshold, acc_norm_threshold: the
            ``TogglingSettings`` of the same names.
        mag_ref_gain: the reference's gain per sample, from ``mag_ref_tau``.
        gravity: g [m/s²] of step 5b's accelerometer check (``data.broad.GRAVITY``).
    """

    use_mag: float
    max_dt: float
    layout: PredictionLayout
    alpha_acc: np.ndarray
    alpha_mag: np.ndarray
    gamma: float
    bias_gain: float
    static_index: int
    bias_gate: float
    mag_disturbance_scale: float
    mag_rejection_factor: float
    noise_weight_acc: float
    noise_weight_mag: float
    confidence_floor: float
    alpha_fallback_acc: float
    alpha_fallback_mag: float
    tan_mag_step: float
    heading_bias_rate: float
    heading_bias_clip: float
    mag_norm_threshold: float
    mag_dip_threshold: float
    mag_ref_gain: float
    acc_norm_threshold: float
    gravity: float


@njit(cache=True, inline="always")
def _gains(params, pred, total):
    """Step 4 on a used prediction: the probability-weighted gains ``(α_a, α_m)``, with
    ``total`` = Σ_s p_s (``filters.prediction.class_evidence``)."""
    aa = 0.0
    am = 0.0
    for s in range(params.layout.n_states):
        p = pred[s]
        aa += p * params.alpha_acc[s]
        am += p * params.alpha_mag[s]
    return aa / total, am / total


@njit(cache=True, inline="always")
def rate_bounded_gain(alpha, v_pred, v_meas, tan_step):
    """Step 5's gain α, lowered where the vector CF step v_new = (1 − α) v + α m would turn v by
    more than the angle θ_max per sample (``tan_step`` = tan θ_max; 0: no bound). The step turns v
    by θ with tan θ = α |v × m| / (v · v_new); over the bound, α solves that equation at θ_max."""
    if tan_step <= 0.0 or alpha <= 0.0:
        return alpha
    cx = v_pred[1] * v_meas[2] - v_pred[2] * v_meas[1]
    cy = v_pred[2] * v_meas[0] - v_pred[0] * v_meas[2]
    cz = v_pred[0] * v_meas[1] - v_pred[1] * v_meas[0]
    cross = math.sqrt(cx * cx + cy * cy + cz * cz)
    vv = v_pred[0] * v_pred[0] + v_pred[1] * v_pred[1] + v_pred[2] * v_pred[2]
    vm = v_pred[0] * v_meas[0] + v_pred[1] * v_meas[1] + v_pred[2] * v_meas[2]
    along = (1.0 - alpha) * vv + alpha * vm
    denominator = cross + tan_step * (vv - vm)
    if alpha * cross <= tan_step * along or denominator <= 0.0:
        return alpha
    return tan_step * vv / denominator


@njit(cache=True, inline="always")
def turn_as(u, v, w):
    """``w`` turned by the shortest-arc rotation that takes the direction of ``u`` to that of ``v`` (any
    lengths; Rodrigues' formula with k = û × v̂, c = û · v̂: R w = c w + k × w + k (k · w) / (1 + c)).
    ``w`` unchanged where u or v is zero or non-finite, or where they are 90° or more apart: a step of
    a_pred that large is no small tilt correction (τ_acc = 0 with a flipped accelerometer), and the
    rotation's axis is ill-defined near 180°."""
    nu = math.sqrt(u[0] * u[0] + u[1] * u[1] + u[2] * u[2])
    nv = math.sqrt(v[0] * v[0] + v[1] * v[1] + v[2] * v[2])
    if not (nu > 0.0 and nv > 0.0 and math.isfinite(nu) and math.isfinite(nv)):
        return w
    ux, uy, uz = u[0] / nu, u[1] / nu, u[2] / nu
    vx, vy, vz = v[0] / nv, v[1] / nv, v[2] / nv
    c = ux * vx + uy * vy + uz * vz
    if not c > 0.0:
        return w
    kx, ky, kz = uy * vz - uz * vy, uz * vx - ux * vz, ux * vy - uy * vx
    kw = (kx * w[0] + ky * w[1] + kz * w[2]) / (1.0 + c)
    return (c * w[0] + ky * w[2] - kz * w[1] + kw * kx,
            c * w[1] + kz * w[0] - kx * w[2] + kw * ky,
            c * w[2] + kx * w[1] - ky * w[0] + kw * kz)


@njit(cache=True, inline="always")
def _unit(v):
    n = math.sqrt(v[0] * v[0] + v[1] * v[1] + v[2] * v[2])
    return (v[0] / n, v[1] / n, v[2] / n)


@njit(cache=True, inline="always")
def _field_accepted(state, params, up, m):
    """Step 5b's field check (VQF's): ``m``'s norm and dip asin(−m̂ · û) (positive where the field points down, as
    the features' δ) against the reference in ``state[14:16]`` (set from the first field, at initialisation); the
    reference follows an accepted field with ``mag_ref_gain``."""
    norm = math.sqrt(m[0] * m[0] + m[1] * m[1] + m[2] * m[2])
    dip = math.asin(max(-1.0, min(1.0, -(m[0] * up[0] + m[1] * up[1] + m[2] * up[2]) / norm)))
    if not state[14] > 0.0:
        state[14], state[15] = norm, dip
    accepted = field_agrees(state[14], state[15], norm, dip, params.mag_norm_threshold, params.mag_dip_threshold)
    if accepted:
        state[14] += params.mag_ref_gain * (norm - state[14])
        state[15] += params.mag_ref_gain * (dip - state[15])
    return accepted


@njit(cache=True, inline="always")
def heading_bias_step(state, params, b, a_pred, a_d, m_before, m_after, m_d):
    """Step 5b: the bias ``b`` [rad/s] fed with the heading correction that turned ``m_before`` into
    ``m_after`` (sensor frame) about the vertical of ``a_pred``, where the field ``m_d`` and the
    accelerometer ``a_d`` pass their checks (module docstring). Returns the new bias."""
    if params.heading_bias_rate <= 0.0 or not vector_ok(a_pred):
        return b
    up = _unit(a_pred)
    field_ok = _field_accepted(state, params, up, m_d)  # first: the reference follows the field either way
    g = math.sqrt(a_d[0] * a_d[0] + a_d[1] * a_d[1] + a_d[2] * a_d[2])
    if not (field_ok and abs(g - params.gravity) < params.acc_norm_threshold * params.gravity):
        return b
    d0 = m_before[0] * up[0] + m_before[1] * up[1] + m_before[2] * up[2]
    d1 = m_after[0] * up[0] + m_after[1] * up[1] + m_after[2] * up[2]
    h0 = (m_before[0] - d0 * up[0], m_before[1] - d0 * up[1], m_before[2] - d0 * up[2])
    h1 = (m_after[0] - d1 * up[0], m_after[1] - d1 * up[1], m_after[2] - d1 * up[2])
    n01 = math.sqrt((h0[0] * h0[0] + h0[1] * h0[1] + h0[2] * h0[2]) * (h1[0] * h1[0] + h1[1] * h1[1] + h1[2] * h1[2]))
    if not n01 > 0.0:
        return b
    # sin θ_h = (h0 × h1) · û / (|h0| |h1|), the turn about the vertical (positive: counter-clockwise from above)
    sin_turn = ((h0[1] * h1[2] - h0[2] * h1[1]) * up[0] + (h0[2] * h1[0] - h0[0] * h1[2]) * up[1]
                + (h0[0] * h1[1] - h0[1] * h1[0]) * up[2]) / n01
    v = sin_turn * params.heading_bias_rate
    new = (b[0] + v * up[0], b[1] + v * up[1], b[2] + v * up[2])
    new_norm2 = new[0] * new[0] + new[1] * new[1] + new[2] * new[2]
    clip2 = params.heading_bias_clip * params.heading_bias_clip
    if new_norm2 > clip2 and new_norm2 > b[0] * b[0] + b[1] * b[1] + b[2] * b[2]:
        return b  # the feed never takes |b| above the clip (a bias learned at rest may be larger)
    return new


@njit(cache=True)
def toggle_step(state, params, gyr, acc, mag, dt, pred, diag):
    """One sample (module docstring, steps 1-7). diag: [alpha_acc, alpha_mag, p_static, bias_norm,
    low_confidence] (1 where a valid prediction was below the confidence floor: step 4's fallback)."""
    use_mag, max_dt, layout = params.use_mag > 0.5, params.max_dt, params.layout
    gamma, bias_gain, static_idx, bias_gate = params.gamma, params.bias_gain, params.static_index, params.bias_gate
    mag_scale = params.mag_disturbance_scale
    # step 4 first: the fallback (filters.prediction, the toggling CF's rule) also stops steps 1 and 3
    valid, top, total = class_evidence(layout, pred)
    status = switch_status(valid, top, total, params.confidence_floor)
    learned = status == LEARNED
    if learned:
        alpha_a, alpha_m = _gains(params, pred, total)
    else:
        alpha_a, alpha_m = params.alpha_fallback_acc, params.alpha_fallback_mag
    eta_ok, a_d, m_d = remove_noise(layout, pred, acc, mag, params.noise_weight_acc, params.noise_weight_mag,
                                    learned)  # step 3
    acc_ok = vector_ok(a_d)
    mag_ok = use_mag and vector_ok(m_d)
    if mag_scale > 0.0 and eta_ok:  # step 4: trust the magnetometer less when a disturbance is predicted,
        # by at most the rejection factor
        e = min(predicted_disturbance(layout, pred, mag_scale), params.mag_rejection_factor - 1.0)
        alpha_m = back_off(alpha_m, e)
    p_static = pred[static_idx] if learned else 0.0
    diag[0] = 0.0
    diag[1] = 0.0
    diag[2] = p_static
    diag[4] = 1.0 if status == LOW_CONFIDENCE else 0.0
    if state[4] < 0.5:  # initialise orientation and vectors from the first valid sample
        ok, q0 = acc_mag_quaternion((1.0, 0.0, 0.0, 0.0), a_d, m_d, mag_ok) if acc_ok else (False, (1.0, 0.0, 0.0, 0.0))
        if ok:
            store_quat(state, q0)
            state[4] = 1.0
            state[8], state[9], state[10] = a_d
            north = rotate_inverse_scalar(q0, (0.0, 1.0, 0.0))  # in 6D m_pred is unused
            state[11], state[12], state[13] = m_d if mag_ok else north
            if mag_ok:  # step 5b's field reference, from the first field
                _field_accepted(state, params, _unit(a_d), m_d)
        return
    q = load_quat(state)
    b = (state[5], state[6], state[7])
    a_pred = (state[8], state[9], state[10])
    m_pred = (state[11], state[12], state[13])
    g_ok = gyro_valid(gyr)  # the raw reading, before the bias correction (filters.base)
    if g_ok and bias_gain > 0.0 and p_static > 0.0:  # step 1
        rx, ry, rz = gyr[0] - b[0], gyr[1] - b[1], gyr[2] - b[2]
        if rx * rx + ry * ry + rz * rz < bias_gate * bias_gate:
            k = bias_gain * p_static
            b = (b[0] + k * rx, b[1] + k * ry, b[2] + k * rz)
    ok_dq, dq = gyro_increment((gyr[0] - b[0], gyr[1] - b[1], gyr[2] - b[2]), dt, max_dt)
    if g_ok and ok_dq:  # step 2
        q = normalize_scalar(multiply_scalar(q, dq))
        a_pred = rotate_inverse_scalar(dq, a_pred)
        m_pred = rotate_inverse_scalar(dq, m_pred)
    if acc_ok:  # step 5
        a_corrected = ((1.0 - alpha_a) * a_pred[0] + alpha_a * a_d[0], (1.0 - alpha_a) * a_pred[1] + alpha_a * a_d[1],
                       (1.0 - alpha_a) * a_pred[2] + alpha_a * a_d[2])
        if use_mag:  # the tilt correction turns the whole frame: the field follows (step 5, "follows")
            m_pred = turn_as(a_pred, a_corrected, m_pred)
        a_pred = a_corrected
        diag[0] = alpha_a
    if mag_ok:
        alpha_m = rate_bounded_gain(alpha_m, m_pred, m_d, params.tan_mag_step)
        m_corrected = ((1.0 - alpha_m) * m_pred[0] + alpha_m * m_d[0], (1.0 - alpha_m) * m_pred[1] + alpha_m * m_d[1],
                       (1.0 - alpha_m) * m_pred[2] + alpha_m * m_d[2])
        if acc_ok:  # step 5b
            b = heading_bias_step(state, params, b, a_pred, a_d, m_pred, m_corrected, m_d)
        m_pred = m_corrected
        diag[1] = alpha_m
    ok, q_am = acc_mag_quaternion(q, a_pred, m_pred, use_mag)  # step 6
    if ok:  # step 7
        c = 1.0 - gamma
        q = normalize_scalar((c * q[0] + gamma * q_am[0], c * q[1] + gamma * q_am[1],
                              c * q[2] + gamma * q_am[2], c * q[3] + gamma * q_am[3]))
    store_quat(state, q)
    state[5], state[6], state[7] = b
    state[8], state[9], state[10] = a_pred
    state[11], state[12], state[13] = m_pred
    diag[3] = math.sqrt(b[0] * b[0] + b[1] * b[1] + b[2] * b[2])


class TogglingFilter(PredictionDrivenFilter):
    """The toggling-gain CF driven by per-sample predictions.

    ``update_batch(gyr, acc, mag, predictions=P)`` with ``P (N, S + 6)``: state
    probabilities then η̂_a, η̂_m (sensor frame, m/s² and µT). ``predictions=None`` means
    "no model": the first state with zero noise (useful only for tests).
    """

    name = "toggling"
    Settings = TogglingSettings
    Coefficients = TogglingCoefficients
    state_names = _STATE
    diagnostic_names = ("alpha_acc", "alpha_mag", "p_static", "bias_norm", "low_confidence")
    step = toggle_step

    @classmethod
    def settings_for(cls, class_names, rest_state: str, **overrides):
        """``PredictionDrivenFilter.settings_for``; the gyro bias is learned in ``rest_state``."""
        return super().settings_for(class_names, rest_state, **{"static_state": rest_state, **overrides})

    def _coefficients(self) -> dict:
        s = self.settings
        ts = self.Ts
        alpha_acc, alpha_mag = np.array([gain(t, ts) for t in s.tau_acc]), np.array([gain(t, ts) for t in s.tau_mag])
        return {"layout": PredictionLayout.of(len(s.states)), "alpha_acc": alpha_acc, "alpha_mag": alpha_mag, "gamma": gain(s.output_tau, ts),
                "bias_gain": gain(s.bias_tau, ts), "static_index": s.states.index(s.static_state),
                "bias_gate": s.bias_gate, "mag_disturbance_scale": s.mag_disturbance_scale,
                "mag_rejection_factor": s.mag_rejection_factor,
                "noise_weight_acc": s.noise_weight_acc, "noise_weight_mag": s.noise_weight_mag,
                "confidence_floor": s.confidence_floor, "alpha_fallback_acc": float(alpha_acc.min()),
                "alpha_fallback_mag": float(alpha_mag.min()), "tan_mag_step": math.tan(s.mag_rate_limit * ts),
                "heading_bias_rate": 1.0 / s.heading_bias_tau if s.heading_bias_tau > 0.0 else 0.0,
                "heading_bias_clip": s.heading_bias_clip, "mag_norm_threshold": s.mag_norm_threshold,
                "mag_dip_threshold": s.mag_dip_threshold, "mag_ref_gain": gain(s.mag_ref_tau, ts),
                "acc_norm_threshold": s.acc_norm_threshold, "gravity": GRAVITY}

    def _default_pred(self, n):
        pred = np.zeros((n, self.n_predictions))
        pred[:, 0] = 1.0
        return pred
