"""The VQF core with learned, motion-dependent time constants.

The VQF core (``filters.vqf_core``) runs unchanged; per sample, the predictions
``pred = [p_1..p_S, η̂_a (3), η̂_m (3)]`` (class probabilities of the motion state, predicted
acc/mag noise in the sensor frame) set the coefficients it uses (a ``CoreModulation``):

1. confidence      c = max_s p_s / Σ_s p_s;   λ = clip((c − c₀) / (1 − c₀), 0, 1)
   (``confidence_floor`` c₀: at or below it the learned values are not trusted at all; the rule,
   and how it differs from the toggling CF's hard switch, is in ``filters.prediction``)
2. time constants  ln τ = λ Σ_s (p_s / Σp) ln τ_s + (1 − λ) ln τ_core     for τ_acc, τ_mag,
   the motion-bias standard deviation σ_motion and the rest thresholds th_ω, th_a (a geometric
   blend: the probabilities mix rates, not seconds); each per-state value is bounded
   (``TAU_ACC_RANGE`` ...), so no state switches a correction off. With ``modulation_tau`` > 0,
   ln τ_acc and ln τ_mag do not jump to these values but follow them with a first-order low-pass
   of that time constant, every sample (``_follow``; why: ``VQFTogglingSettings``)
3. coefficients    the τ_acc Butterworth low-pass, k_mag = 1 − exp(−Ts/τ_mag),
   W_motion = σ⁴/V + σ² and th² from the blended values, exactly as the core derives its own (B5);
   with a predicted magnetic disturbance (9D, σ_m > 0, the toggling CF's law of step 4, bounded)
   k_mag ← k_mag / (1 + e), e = min((|η̂_m| / σ_m)², f_reject − 1): the heading correction backs
   off where the models predict a disturbed field, by at most the core's own rejection factor
   f_reject (VQF's 2: what the core itself does once its rejection time is spent, M4), so the
   learned part can slow the heading correction but never stop it (per sample; on top of the
   core's own norm/dip rejection M1–M4). ``mag_backoff_measured`` instead caps e by the deviation
   the magnetometer shows against the core's reference field, (|m − m_ref|_min / σ_m)²
   3b. field change (9D, σ_f > 0, nothing learned): the field in the earth frame of the core's 6D
   orientation, m_E = R(q_6D) m, against its own first-order low-pass of time constant τ_f,
   e_f = min((|m_E − LP(m_E)| / σ_f)², f_reject − 1); the back-off uses max(e, e_f). The gyroscope
   explains the field's turning, so an undisturbed field keeps e_f at the sensor's floor; a
   disturbance coming, going or moving with the sensor raises it. Updated after each sample's
   core step (the next sample backs off on it), not before τ_f of valid samples
4. noise removal   a_d = a − w_a η̂_a,  m_d = m − w_m η̂_m   (w learned in [0, 1])
5. the core step on (ω, a_d, m_d) with those coefficients.

Steps 1–3 run only when the prediction changes (every hop of the in-loop models), so the
per-sample cost is the core's. Without a prediction (NaN probabilities: before the first
full window, or a model that failed) the core's own settings are used: the *fallback*, which is
also what low confidence moves toward. With every per-state value equal to the core's, the
filter *is* the core (test): learning switched off.

Parameters are physical (seconds, °/s), so a learned setting means the same at any rate.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, fields
from typing import NamedTuple, get_type_hints

import numpy as np
from numba import njit

from togglecf.core.quaternion import multiply_scalar, rotate_scalar
from togglecf.filters.base import load_quat, record_fields, record_of, record_view, state_record, vector_ok
from togglecf.filters.prediction import (
    PredictionDrivenFilter,
    PredictionLayout,
    back_off,
    blend_trust,
    class_evidence,
    predicted_disturbance,
    remove_noise,
)
from togglecf.filters.timeconst import gain_from_tau
from togglecf.filters.vqf_core import (
    CORE_STATE_FIELDS,
    CoreModulation,
    VQFCoreCoefficients,
    VQFCoreFilter,
    VQFCoreSettings,
    align_q_acc,
    bias_noise_w,
    core_coefficients,
    core_update,
    lp_coefficients,
    reset_core_state,
)

__all__ = ["VQFTogglingFilter", "VQFTogglingSettings", "VQFTogglingCoefficients", "vqf_toggling_step",
           "TAU_ACC_RANGE", "TAU_MAG_RANGE", "BIAS_SIGMA_MOTION_RANGE", "REST_TH_GYR_RANGE", "REST_TH_ACC_RANGE",
           "MAX_STATES"]

_DEG = math.pi / 180.0

#: bounds [s] of a per-state τ_acc: the inclination correction is never faster than 0.3 s nor off
TAU_ACC_RANGE = (0.3, 60.0)
#: bounds [s] of a per-state τ_mag
TAU_MAG_RANGE = (0.5, 200.0)
#: bounds [°/s] of a per-state σ_motion (bias estimation in motion: never frozen, never wild)
BIAS_SIGMA_MOTION_RANGE = (0.01, 2.0)
#: bounds [°/s] of a per-state rest threshold th_ω (rest detection never off, never everywhere)
REST_TH_GYR_RANGE = (0.5, 10.0)
#: bounds [m/s²] of a per-state rest threshold th_a
REST_TH_ACC_RANGE = (0.1, 3.0)
#: the core's setting of each per-state field of ``VQFTogglingSettings``
_PER_STATE = {"tau_acc": "tau_acc_states", "tau_mag": "tau_mag_states", "bias_sigma_motion": "bias_sigma_motion_states",
              "rest_th_gyr": "rest_th_gyr_states", "rest_th_acc": "rest_th_acc_states"}
#: most motion states a model may have (the state keeps the last probabilities to see changes)
MAX_STATES = 8


@dataclass(frozen=True)
class VQFTogglingSettings(VQFCoreSettings):
    """The core's settings (``VQFCoreSettings``: its values are the fallback) plus, per motion state:

    Attributes:
        states: motion-state names, in the order of the classifier's classes.
        tau_acc_states: τ_acc [s] per state (default: the core's ``tau_acc`` for all).
        tau_mag_states: τ_mag [s] per state (default: the core's ``tau_mag``).
        bias_sigma_motion_states: σ_motion [°/s] per state (default: the core's).
        rest_th_gyr_states: rest threshold th_ω [°/s] per state (default: the core's ``rest_th_gyr``).
        rest_th_acc_states: rest threshold th_a [m/s²] per state (default: the core's ``rest_th_acc``).
        confidence_floor: c₀ in [0, 1) of step 1; 0 trusts every prediction fully.
        mag_disturbance_scale: σ_m [µT] of step 3: the heading gain is divided by
            1 + min((|η̂_m| / σ_m)², f_reject − 1) (9D), f_reject the core's
            ``mag_rejection_factor``; 0 (default) = off.
        noise_weight_acc, noise_weight_mag: w_a, w_m in [0, 1] of step 4 (default 0: off).
        modulation_tau: time constant [s] with which ln τ_acc and ln τ_mag follow their blended
            values of step 2 (a first-order low-pass at the filter's rate); 0 (default): at once.
            Why: the τ_acc low-pass is a running average whose weights are its gains; gains that
            change from hop to hop with predictions made from the same signal weight the signal
            by its own content, which biases the average (the inclination). Changing a time
            constant no faster than the time scale it sets keeps the average unbiased.
        mag_backoff_measured: False (default): the back-off of step 3 on the predicted
            disturbance, bounded by the core's rejection factor (the heading gain is at least
            k_mag / f_reject). True: on at most the disturbance the magnetometer itself shows
            against the core's reference field (for models whose gains.json stores it;
            it keeps no gain where the core's reference is itself disturbed, e.g. a magnet
            attached from the start).
        field_change_scale: σ_f [µT] of step 3b: the heading gain also backs off on how much the
            field changed in the earth frame of the core's 6D orientation (9D); 0 (default) = off.
        field_change_tau: τ_f [s] of step 3b: the time constant of the low-pass the field is
            compared with, and the valid samples' time before it backs off at all (default 1 s).
    """

    states: tuple = ("static", "dynamic")
    tau_acc_states: tuple = ()
    tau_mag_states: tuple = ()
    bias_sigma_motion_states: tuple = ()
    rest_th_gyr_states: tuple = ()
    rest_th_acc_states: tuple = ()
    confidence_floor: float = 0.0
    mag_disturbance_scale: float = 0.0
    noise_weight_acc: float = 0.0
    noise_weight_mag: float = 0.0
    modulation_tau: float = 0.0
    mag_backoff_measured: bool = False
    field_change_scale: float = 0.0
    field_change_tau: float = 1.0

    def __post_init__(self):
        super().__post_init__()
        n = len(self.states)
        object.__setattr__(self, "states", tuple(self.states))
        if not 1 <= n <= MAX_STATES:
            raise ValueError(f"states: 1 to {MAX_STATES} motion states, got {n}")
        for name, core, (lo, hi) in (("tau_acc_states", self.tau_acc, TAU_ACC_RANGE),
                                     ("tau_mag_states", self.tau_mag, TAU_MAG_RANGE),
                                     ("bias_sigma_motion_states", self.bias_sigma_motion, BIAS_SIGMA_MOTION_RANGE),
                                     ("rest_th_gyr_states", self.rest_th_gyr, REST_TH_GYR_RANGE),
                                     ("rest_th_acc_states", self.rest_th_acc, REST_TH_ACC_RANGE)):
            vals = tuple(float(v) for v in getattr(self, name)) or (float(core),) * n
            object.__setattr__(self, name, vals)
            if len(vals) != n:
                raise ValueError(f"{name} needs one value per state {self.states}, got {vals}")
            if not all(lo <= v <= hi for v in vals):
                raise ValueError(f"{name} must lie in [{lo}, {hi}] (a state may not switch the correction off), "
                                 f"got {vals}")
        if not (self.mag_disturbance_scale >= 0.0 and math.isfinite(self.mag_disturbance_scale)):
            raise ValueError(f"mag_disturbance_scale must be >= 0 µT (0: off), got {self.mag_disturbance_scale}")
        if not 0.0 <= self.confidence_floor < 1.0:
            raise ValueError(f"confidence_floor must be in [0, 1), got {self.confidence_floor}")
        if not (0.0 <= self.noise_weight_acc <= 1.0 and 0.0 <= self.noise_weight_mag <= 1.0):
            raise ValueError("noise weights must be in [0, 1]")
        if not (self.modulation_tau >= 0.0 and math.isfinite(self.modulation_tau)):
            raise ValueError(f"modulation_tau must be a finite time constant >= 0 s, got {self.modulation_tau}")
        if self.tau_mag == 0.0:
            raise ValueError("tau_mag must be > 0 s for the learned filter (its blend is in ln τ)")
        if not (self.field_change_scale >= 0.0 and math.isfinite(self.field_change_scale)):
            raise ValueError(f"field_change_scale must be >= 0 µT (0: off), got {self.field_change_scale}")
        if not (self.field_change_tau > 0.0 and math.isfinite(self.field_change_tau)):
            raise ValueError(f"field_change_tau must be a finite time constant > 0 s, got {self.field_change_tau}")

    def learning_off(self, use_mag: bool) -> bool:
        """True when nothing learned acts in 9D (``use_mag``) or 6D: every per-state value equals the
        core's (τ_acc, τ_mag, σ_motion, th_ω, th_a), no noise vector is subtracted (w_a = 0, and in 9D
        w_m = 0) and, in 9D, the heading back-offs are off (σ_m = 0, σ_f = 0). Then the confidence floor
        and ``modulation_tau`` change nothing (every blend is the core's value) and the filter is the core
        with ``core_settings`` (within rounding of exp(ln τ)): ``LearnedVQF`` and the C export run the
        core alone."""
        mag_terms = use_mag and (self.noise_weight_mag != 0.0 or self.mag_disturbance_scale != 0.0
                                 or self.field_change_scale != 0.0)
        return self.states_off() and self.noise_weight_acc == 0.0 and not mag_terms

    def states_off(self) -> bool:
        """True when every per-state value equals the core's (τ_acc, τ_mag, σ_motion, th_ω, th_a): the
        blend of step 2 is then the core's value whatever the class probabilities (within rounding of
        the sum of the weights), so the classifier changes nothing."""
        return all(v == getattr(self, core) for core, per_state in _PER_STATE.items()
                   for v in getattr(self, per_state))

    @property
    def core_settings(self) -> VQFCoreSettings:
        """The fallback: the core's own settings (learning off)."""
        return VQFCoreSettings(**{f.name: getattr(self, f.name) for f in fields(VQFCoreSettings)})


#: the core's coefficients, then the learned ones (logarithms of the per-state values, rad for σ)
VQFTogglingCoefficients = NamedTuple("VQFTogglingCoefficients", [
    *get_type_hints(VQFCoreCoefficients).items(),
    ("layout", PredictionLayout), ("ln_tau_acc", np.ndarray), ("ln_tau_mag", np.ndarray), ("ln_sigma_motion", np.ndarray),
    ("ln_rest_th_gyr", np.ndarray), ("ln_rest_th_acc", np.ndarray),
    ("ln_tau_acc_core", float), ("ln_tau_mag_core", float), ("ln_sigma_motion_core", float),
    ("ln_rest_th_gyr_core", float), ("ln_rest_th_acc_core", float),
    ("confidence_floor", float), ("mag_disturbance_scale", float), ("noise_weight_acc", float),
    ("noise_weight_mag", float), ("modulation_gain", float), ("mag_backoff_measured", float),
    ("field_change_scale", float), ("field_change_tau", float), ("field_change_gain", float)])

#: the core's state, then the modulation in use (a ``CoreModulation`` record), τ_acc, τ_mag and λ in
#: use (diagnostics), the last prediction row (to see changes), the targets and followed ln τ_acc,
#: ln τ_mag (``_follow``), the heading back-off (``_heading_gain``) and k_mag of τ_mag in use before
#: the back-off (computed when τ_mag moves, not every sample); step 3b's low-passed earth-frame field
#: [µT], the time [s] of valid samples it has seen (−1: none yet) and its disturbance e_f
STATE_FIELDS = CORE_STATE_FIELDS + (
    ("mod", record_fields(CoreModulation, "mod_")),
    ("tau_acc_now", "tau_acc_now"), ("tau_mag_now", "tau_mag_now"), ("trust_now", "trust_now"),
    ("last_p", tuple(f"last_p{s}" for s in range(PredictionLayout.of(MAX_STATES).size))),
    ("ln_tau_acc_target", "ln_tau_acc_target"), ("ln_tau_mag_target", "ln_tau_mag_target"),
    ("ln_tau_acc_now", "ln_tau_acc_now"), ("ln_tau_mag_now", "ln_tau_mag_now"),
    ("mag_disturbance_predicted", "mag_disturbance_predicted"), ("mag_backoff", "mag_backoff"),
    ("k_mag_now", "k_mag_now"),
    ("field_lp", ("field_lp_x", "field_lp_y", "field_lp_z")), ("field_lp_t", "field_lp_t"),
    ("field_change_disturbance", "field_change_disturbance"))
VQFT_STATE, _STATE_NAMES = state_record(STATE_FIELDS)
_vqft_state = record_view(VQFT_STATE)
_DIAG_NAMES = VQFCoreFilter.diagnostic_names + ("tau_acc", "tau_mag", "trust")
N_CORE_DIAG = len(VQFCoreFilter.diagnostic_names)


@njit(cache=True, inline="always")
def _prediction_changed(st, pred, n):
    """True when the first ``n`` entries of ``pred`` differ from the last ones (NaN equals NaN)."""
    for s in range(n):
        a, b = pred[s], st.last_p[s]
        if a != b and not (a != a and b != b):
            return True
    return False


@njit(cache=True)
def modulate(st, p, pred):
    """Steps 1–3: blend the per-state values with the probabilities in ``pred`` and store the
    resulting ``CoreModulation`` (and the prediction) in the state record. Returns (τ_acc, τ_mag, λ)."""
    layout = p.layout
    for s in range(layout.size):
        st.last_p[s] = pred[s]
    valid, top, total = class_evidence(layout, pred)  # step 1 (filters.prediction)
    lam = blend_trust(valid, top, total, p.confidence_floor)  # the learned VQF's fallback rule: λ = 0, the core
    la, lm, ls = p.ln_tau_acc_core, p.ln_tau_mag_core, p.ln_sigma_motion_core
    lg, lc = p.ln_rest_th_gyr_core, p.ln_rest_th_acc_core
    if valid:
        ma, mm, msg, mg, mc = 0.0, 0.0, 0.0, 0.0, 0.0
        for s in range(layout.n_states):  # step 2
            w = pred[s] / total
            ma += w * p.ln_tau_acc[s]
            mm += w * p.ln_tau_mag[s]
            msg += w * p.ln_sigma_motion[s]
            mg += w * p.ln_rest_th_gyr[s]
            mc += w * p.ln_rest_th_acc[s]
        la = lam * ma + (1.0 - lam) * la
        lm = lam * mm + (1.0 - lam) * lm
        ls = lam * msg + (1.0 - lam) * ls
        lg = lam * mg + (1.0 - lam) * lg
        lc = lam * mc + (1.0 - lam) * lc
    tau_acc, tau_mag = math.exp(la), math.exp(lm)
    w_motion = bias_noise_w(math.exp(ls), p.bias_v)  # step 3
    e_pred = 0.0  # the predicted disturbance (|η̂_m| / σ_m)² (no prediction: NaN, none)
    if p.mag_disturbance_scale > 0.0:
        e_pred = predicted_disturbance(layout, pred, p.mag_disturbance_scale)
    m = st.mod
    if p.modulation_gain >= 1.0:  # else τ_acc's low-pass and k_mag follow (_follow, _heading_gain)
        acc_lp = lp_coefficients(tau_acc, p.ts)
        m.acc_lp.k, m.acc_lp.decay = acc_lp.k, acc_lp.decay
        m.k_mag = gain_from_tau(tau_mag, p.ts)  # the back-off (e_pred): _heading_gain, every sample
    m.bias_w_motion = w_motion
    m.bias_w_vertical = w_motion * (p.modulation.bias_w_vertical / p.modulation.bias_w_motion)
    m.rest_th_gyr_sq = math.exp(2.0 * lg)
    m.rest_th_acc_sq = math.exp(2.0 * lc)
    st.ln_tau_acc_target, st.ln_tau_mag_target, st.mag_disturbance_predicted = la, lm, e_pred
    return tau_acc, tau_mag, lam


@njit(cache=True)
def _follow(st, p):
    """``modulation_tau``: ln τ_acc and ln τ_mag one step towards their targets (first-order
    low-pass), the τ_acc low-pass coefficients recomputed while ln τ_acc moves, k_mag before the
    back-off (``k_mag_now``) while ln τ_mag moves."""
    k = p.modulation_gain
    la, lm = st.ln_tau_acc_now, st.ln_tau_mag_now
    ta, tm = st.ln_tau_acc_target, st.ln_tau_mag_target
    if la != ta:
        la += k * (ta - la)
        if abs(ta - la) < 1e-9:
            la = ta
        st.ln_tau_acc_now = la
        tau_acc = math.exp(la)
        acc_lp = lp_coefficients(tau_acc, p.ts)
        st.mod.acc_lp.k, st.mod.acc_lp.decay = acc_lp.k, acc_lp.decay
        st.tau_acc_now = tau_acc
    if lm != tm:
        lm += k * (tm - lm)
        if abs(tm - lm) < 1e-9:
            lm = tm
        st.ln_tau_mag_now = lm
        st.tau_mag_now = math.exp(lm)
        st.k_mag_now = gain_from_tau(st.tau_mag_now, p.ts)
        st.mod.k_mag = st.k_mag_now  # without a back-off, the gain in use (_heading_gain divides it)


@njit(cache=True, inline="always")
def _field_deviation_sq(st, mag):
    """The disturbance the magnetometer shows [µT²]: the least |m − m_ref|² over the unknown
    azimuth, from the field norm n and dip d of ``mag`` (dip in the previous sample's earth frame)
    and the core's reference n_ref, d_ref (M2): n² + n_ref² − 2 n n_ref cos(d − d_ref). 0 while
    the core has no reference yet, or for an invalid sample."""
    n_ref = st.mag_ref_norm
    n2 = mag[0] * mag[0] + mag[1] * mag[1] + mag[2] * mag[2]
    if not (n_ref > 0.0 and n2 > 0.0 and n2 < math.inf):
        return 0.0
    n = math.sqrt(n2)
    q = st.quat
    mz = rotate_scalar((q[0], q[1], q[2], q[3]), (mag[0], mag[1], mag[2]))[2]
    dip = -math.asin(min(max(mz / n, -1.0), 1.0))
    return max(n2 + n_ref * n_ref - 2.0 * n * n_ref * math.cos(dip - st.mag_ref_dip), 0.0)


@njit(cache=True, inline="always")
def _heading_gain(st, p, mag):
    """Step 3's k_mag for this sample: the followed τ_mag's gain (``k_mag_now``) divided by the back-off
    1 + e, e = (|η̂_m| / σ_m)² at most f_reject − 1 (the core's rejection factor: the learned
    back-off slows the heading correction no more than the core's own, M4), or with
    ``mag_backoff_measured`` at most the disturbance the magnetometer itself shows,
    (|m − m_ref|_min / σ_m)² (``_field_deviation_sq``); then the larger of that and step 3b's e_f
    (``_field_change``), itself at most f_reject − 1."""
    cap = max(p.mag_rejection_factor - 1.0, 0.0)
    e = st.mag_disturbance_predicted
    if e > 0.0:
        if p.mag_backoff_measured > 0.5:
            e = min(e, _field_deviation_sq(st, mag) / (p.mag_disturbance_scale * p.mag_disturbance_scale))
        else:
            e = min(e, cap)
    e_f = st.field_change_disturbance
    if e_f > 0.0:
        e = max(e, min(e_f, cap))
    st.mag_backoff = 1.0 + e
    st.mod.k_mag = back_off(st.k_mag_now, e)


@njit(cache=True, inline="always")
def _field_change(st, p, mag):
    """Step 3b after the core step: the field ``mag`` [µT] in the earth frame of the core's 6D
    orientation, m_E = R(q_acc ⊗ q_gyr) m, against its low-pass (gain ``field_change_gain``); e_f =
    (|m_E − LP| / σ_f)², 0 until the low-pass has seen ``field_change_tau`` of valid samples. An invalid
    sample changes nothing (the policy of ``filters.base``)."""
    if not vector_ok(mag):
        return
    me = rotate_scalar(multiply_scalar(load_quat(st.q_acc), load_quat(st.q_gyr)), (mag[0], mag[1], mag[2]))
    lp = st.field_lp
    if st.field_lp_t < 0.0:  # the first valid sample starts the low-pass
        lp[0], lp[1], lp[2] = me[0], me[1], me[2]
        st.field_lp_t = 0.0
        return
    d0, d1, d2 = me[0] - lp[0], me[1] - lp[1], me[2] - lp[2]
    st.field_lp_t += p.ts
    if st.field_lp_t >= p.field_change_tau - 0.5 * p.ts:  # half a sample: float32 (C) sums agree
        st.field_change_disturbance = (d0 * d0 + d1 * d1 + d2 * d2) / (p.field_change_scale * p.field_change_scale)
    k = p.field_change_gain
    lp[0], lp[1], lp[2] = lp[0] + k * d0, lp[1] + k * d1, lp[2] + k * d2


@njit(cache=True)
def vqf_toggling_step(state, params, gyr, acc, mag, dt, pred, diag):
    """One sample (module docstring, steps 1–5). diag: the core's, then τ_acc [s], τ_mag [s] and
    the trust λ in the learned values (0: fallback to the core)."""
    p = params
    st = _vqft_state(state)
    layout = p.layout
    if _prediction_changed(st, pred, layout.size if p.mag_disturbance_scale > 0.0 else layout.n_states):
        tau_acc, tau_mag, lam = modulate(st, p, pred)
        st.trust_now = lam
        if p.modulation_gain >= 1.0:
            st.tau_acc_now, st.tau_mag_now = tau_acc, tau_mag
            st.k_mag_now = st.mod.k_mag  # modulate's gain_from_tau(tau_mag), before any back-off
    if p.modulation_gain < 1.0:
        _follow(st, p)
    if p.mag_disturbance_scale > 0.0 or p.field_change_scale > 0.0:  # else modulate or _follow set k_mag
        _heading_gain(st, p, mag)
    # step 4, the learned VQF's rule (filters.prediction): whenever η̂ is finite; with both weights 0 the
    # sample as is (a − 0 η̂ = a), without the per-sample check, as the C export
    a_d, m_d = (acc[0], acc[1], acc[2]), (mag[0], mag[1], mag[2])
    if p.noise_weight_acc != 0.0 or p.noise_weight_mag != 0.0:
        _, a_d, m_d = remove_noise(layout, pred, acc, mag, p.noise_weight_acc, p.noise_weight_mag, True)
    core_update(st, p, st.mod, gyr, a_d, m_d, dt, diag)  # step 5
    if p.field_change_scale > 0.0:  # step 3b for the next sample
        _field_change(st, p, m_d)
    diag[N_CORE_DIAG], diag[N_CORE_DIAG + 1], diag[N_CORE_DIAG + 2] = st.tau_acc_now, st.tau_mag_now, st.trust_now


class VQFTogglingFilter(PredictionDrivenFilter):
    """The VQF core with learned time constants, driven by per-sample predictions:
    ``VQFTogglingFilter(fs, settings).update_batch(gyr, acc, mag, predictions=P)`` with
    ``P (N, S + 6)``. ``predictions=None`` means "no model": NaN rows, i.e. the core itself.
    Diagnostics: the core's, plus ``tau_acc``, ``tau_mag`` [s] and ``trust`` (λ of step 1). The core's
    parts (coefficients, initial state, ``set_quat``) are the core's own functions (``filters.vqf_core``).
    """

    name = "vqf_toggling"
    Settings = VQFTogglingSettings
    Coefficients = VQFTogglingCoefficients
    state_names = _STATE_NAMES
    state_dtype = VQFT_STATE
    diagnostic_names = _DIAG_NAMES
    step = vqf_toggling_step

    def _coefficients(self) -> dict:
        s = self.settings
        core = core_coefficients(s, self.Ts)
        return {**core, "layout": PredictionLayout.of(len(s.states)), "ln_tau_acc": np.log(np.array(s.tau_acc_states)),
                "ln_tau_mag": np.log(np.array(s.tau_mag_states)),
                "ln_sigma_motion": np.log(np.array(s.bias_sigma_motion_states) * _DEG),
                "ln_rest_th_gyr": np.log(np.array(s.rest_th_gyr_states) * _DEG),
                "ln_rest_th_acc": np.log(np.array(s.rest_th_acc_states)),
                "ln_tau_acc_core": math.log(s.tau_acc), "ln_tau_mag_core": math.log(s.tau_mag),
                "ln_sigma_motion_core": math.log(s.bias_sigma_motion * _DEG),
                "ln_rest_th_gyr_core": math.log(s.rest_th_gyr * _DEG), "ln_rest_th_acc_core": math.log(s.rest_th_acc),
                "confidence_floor": s.confidence_floor,
                "mag_disturbance_scale": s.mag_disturbance_scale if self.use_mag else 0.0,
                "noise_weight_acc": s.noise_weight_acc, "noise_weight_mag": s.noise_weight_mag,
                "modulation_gain": gain_from_tau(s.modulation_tau, self.Ts),
                "mag_backoff_measured": float(s.mag_backoff_measured),
                "field_change_scale": s.field_change_scale if self.use_mag else 0.0,
                "field_change_tau": s.field_change_tau,
                "field_change_gain": gain_from_tau(s.field_change_tau, self.Ts)}

    @property
    def record(self):
        """The state as a named record (``VQFT_STATE``): a view, writes go to ``state``."""
        return record_of(self.state, self.state_dtype)

    @property
    def uses_class_probabilities(self) -> bool:
        """False when every per-state value is the core's (``VQFTogglingSettings.states_off``)."""
        return not self.settings.states_off()

    def reset(self):
        """The core's initial state (``reset_core_state``); the modulation starts at the core's own
        coefficients (no prediction seen yet: NaN probabilities)."""
        super().reset()
        st = self.record
        reset_core_state(st, self.params)
        _store_record(st.mod, self.params.modulation)
        st.tau_acc_now, st.tau_mag_now, st.trust_now = self.settings.tau_acc, self.settings.tau_mag, 0.0
        st.last_p[:] = np.nan
        st.ln_tau_acc_target = st.ln_tau_acc_now = math.log(self.settings.tau_acc)
        st.ln_tau_mag_target = st.ln_tau_mag_now = math.log(self.settings.tau_mag)
        st.mag_disturbance_predicted, st.mag_backoff = 0.0, 1.0
        st.k_mag_now = st.mod.k_mag  # the core's own, before any back-off
        st.field_lp[:] = 0.0
        st.field_lp_t, st.field_change_disturbance = -1.0, 0.0  # step 3b: no valid field seen yet

    def set_quat(self, q):
        """Set the output orientation (sensor -> ENU) and mark the filter initialised; the core's
        q_acc absorbs the change (``filters.vqf_core.align_q_acc``)."""
        super().set_quat(q)
        align_q_acc(self.record, self.use_mag)

    def _default_pred(self, n):
        return np.full((n, self.n_predictions), np.nan)


def _store_record(rec, values):
    """Copy the ``NamedTuple`` ``values`` into the record ``rec`` with the same fields (nested ones too)."""
    for name, v in values._asdict().items():
        if isinstance(v, tuple):
            _store_record(rec[name], v)
        else:
            rec[name] = v
