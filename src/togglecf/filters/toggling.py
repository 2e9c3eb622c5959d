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
   magnetometer gain also falls with the predicted disturbance: α_m / (1 + (|η̂_m| / σ_m)²)
5. vector CF step           a_pred ← (1 − α_a) a_pred + α_a a_d,   m_pred likewise with α_m
6. acc/mag orientation      q_am = from_acc_mag(a_pred, m_pred)   (6D: q_g tilted onto a_pred)
7. output blend             q = normalize((1 − γ) q_g + γ q_am)    (LERP on the short arc)

Why this geometric form: blending the *vectors* (step 5) gives tilt and heading their own
gains (``from_acc_mag`` takes tilt from a_pred only and heading from m_pred's horizontal
part), and the LERP of step 7 is the quaternion equivalent of projecting
``(1 − γ) R_g + γ R_am`` back onto a rotation (both agree to first order in the angle
between them; LERP stays exactly unit-norm after normalising). γ = 1 makes the orientation
a pure function of the two gyro-propagated vectors; γ < 1 adds a second smoothing stage.

Bad samples follow the policy of ``filters.base`` (non-finite or saturated gyro, bad Δt: no propagation;
bad acc: no tilt update; bad mag: no heading update). Non-finite predictions count as
"no prediction": the probabilities of the last valid hop are kept (caller's job) and η̂ = 0.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numba import njit

from .base import (GYRO_FULL_SCALE, FilterSettings, OrientationFilter, acc_mag_quaternion, gyro_increment, load_quat,
                   store_quat, vector_ok)
from ..quaternion import multiply_scalar, normalize_scalar, rotate_inverse_scalar

__all__ = ["TogglingFilter", "TogglingSettings", "toggle_step", "N_PRED_NOISE"]

N_PRED_NOISE = 6  # η̂_a (3) then η̂_m (3)
_STATE = ("bias_x", "bias_y", "bias_z", "a_pred_x", "a_pred_y", "a_pred_z", "m_pred_x", "m_pred_y", "m_pred_z")


@dataclass(frozen=True)
class TogglingSettings(FilterSettings):
    """Attributes:
        states: motion-state names, in the order of the classifier's classes.
        alpha_acc: per-state weight of the denoised accelerometer per sample, in [0, 1].
        alpha_mag: per-state weight of the denoised magnetometer per sample, in [0, 1].
        gamma: output blend weight of the acc/mag orientation (1: vectors only), in (0, 1].
        static_state: name of the state in which the gyro bias is learned.
        bias_gain: per-sample low-pass gain of the bias estimate at p_static = 1 (0 disables).
        bias_gate: largest |ω − b| [rad/s] still taken as bias (rejects slow motion at "rest").
        mag_disturbance_scale: σ_m [µT] of step 4; 0 turns the disturbance scaling off.
        noise_weight_acc, noise_weight_mag: w_a, w_m of step 3, in [0, 1].
    The defaults are placeholders for a two-state model; ``togglecf train`` learns the gains
    on the training trials and stores them with the models.
    """

    states: tuple = ("static", "dynamic")
    alpha_acc: tuple = (0.01, 0.0005)
    alpha_mag: tuple = (0.002, 0.0005)
    gamma: float = 1.0
    static_state: str = "static"
    bias_gain: float = 0.002
    bias_gate: float = 0.05
    mag_disturbance_scale: float = 0.0
    noise_weight_acc: float = 1.0
    noise_weight_mag: float = 1.0

    def __post_init__(self):
        super().__post_init__()
        n = len(self.states)
        object.__setattr__(self, "states", tuple(self.states))
        object.__setattr__(self, "alpha_acc", tuple(float(a) for a in self.alpha_acc))
        object.__setattr__(self, "alpha_mag", tuple(float(a) for a in self.alpha_mag))
        if n < 1 or len(self.alpha_acc) != n or len(self.alpha_mag) != n:
            raise ValueError(f"alpha_acc and alpha_mag need one gain per state {self.states}")
        for name in ("alpha_acc", "alpha_mag"):
            if not all(0.0 <= a <= 1.0 and math.isfinite(a) for a in getattr(self, name)):
                raise ValueError(f"{name} gains must be in [0, 1], got {getattr(self, name)}")
        if not 0.0 < self.gamma <= 1.0:
            raise ValueError(f"gamma must be in (0, 1], got {self.gamma}")
        if self.static_state not in self.states:
            raise ValueError(f"static_state {self.static_state!r} is not one of {self.states}")
        if not (0.0 <= self.noise_weight_acc <= 1.0 and 0.0 <= self.noise_weight_mag <= 1.0):
            raise ValueError("noise weights must be in [0, 1]")
        if self.mag_disturbance_scale < 0.0:
            raise ValueError(f"mag_disturbance_scale must be >= 0 µT, got {self.mag_disturbance_scale}")
        if not (0.0 <= self.bias_gain <= 1.0 and self.bias_gate >= 0.0):
            raise ValueError("bias_gain must be in [0, 1] and bias_gate >= 0")


@njit(cache=True, inline="always")
def _gains(params, pred, ns):
    """Probability-weighted gains (step 4); a non-finite probability row counts as the static
    state's gains being off: the lowest gain of each sensor is used (the cautious choice)."""
    aa = 0.0
    am = 0.0
    total = 0.0
    for s in range(ns):
        p = pred[s]
        if not (p >= 0.0):
            aa = params[3]
            am = params[3 + ns]
            for t in range(ns):
                aa = min(aa, params[3 + t])
                am = min(am, params[3 + ns + t])
            return aa, am, 0.0
        aa += p * params[3 + s]
        am += p * params[3 + ns + s]
        total += p
    if total > 0.0:
        aa /= total
        am /= total
    return aa, am, total


@njit(cache=True)
def toggle_step(state, params, gyr, acc, mag, dt, pred, diag):
    """One sample (module docstring, steps 1-7). diag: [alpha_acc, alpha_mag, p_static, bias_norm]."""
    use_mag, max_dt, ns = params[0] > 0.5, params[1], int(params[2])
    o = 3 + 2 * ns
    gamma, bias_gain, static_idx, bias_gate = params[o], params[o + 1], int(params[o + 2]), params[o + 3]
    mag_scale, w_a, w_m = params[o + 4], params[o + 5], params[o + 6]
    eta_ok = True
    for j in range(N_PRED_NOISE):
        if not math.isfinite(pred[ns + j]):
            eta_ok = False
    if eta_ok:  # step 3
        a_d = (acc[0] - w_a * pred[ns], acc[1] - w_a * pred[ns + 1], acc[2] - w_a * pred[ns + 2])
        m_d = (mag[0] - w_m * pred[ns + 3], mag[1] - w_m * pred[ns + 4], mag[2] - w_m * pred[ns + 5])
    else:
        a_d = (acc[0], acc[1], acc[2])
        m_d = (mag[0], mag[1], mag[2])
    acc_ok = vector_ok(a_d)
    mag_ok = use_mag and vector_ok(m_d)
    alpha_a, alpha_m, _ = _gains(params, pred, ns)
    if mag_scale > 0.0 and eta_ok:  # step 4: trust the magnetometer less when a disturbance is predicted
        e2 = pred[ns + 3] * pred[ns + 3] + pred[ns + 4] * pred[ns + 4] + pred[ns + 5] * pred[ns + 5]
        alpha_m = alpha_m / (1.0 + e2 / (mag_scale * mag_scale))
    p_static = pred[static_idx] if pred[static_idx] >= 0.0 else 0.0
    diag[0] = 0.0
    diag[1] = 0.0
    diag[2] = p_static
    if state[4] < 0.5:  # initialise orientation and vectors from the first valid sample
        ok, q0 = acc_mag_quaternion((1.0, 0.0, 0.0, 0.0), a_d, m_d, mag_ok) if acc_ok else (False, (1.0, 0.0, 0.0, 0.0))
        if ok:
            store_quat(state, q0)
            state[4] = 1.0
            state[8], state[9], state[10] = a_d
            north = rotate_inverse_scalar(q0, (0.0, 1.0, 0.0))  # in 6D m_pred is unused
            state[11], state[12], state[13] = m_d if mag_ok else north
        return
    q = load_quat(state)
    b = (state[5], state[6], state[7])
    a_pred = (state[8], state[9], state[10])
    m_pred = (state[11], state[12], state[13])
    g_ok = abs(gyr[0]) < GYRO_FULL_SCALE and abs(gyr[1]) < GYRO_FULL_SCALE and abs(gyr[2]) < GYRO_FULL_SCALE
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
        a_pred = ((1.0 - alpha_a) * a_pred[0] + alpha_a * a_d[0], (1.0 - alpha_a) * a_pred[1] + alpha_a * a_d[1],
                  (1.0 - alpha_a) * a_pred[2] + alpha_a * a_d[2])
        diag[0] = alpha_a
    if mag_ok:
        m_pred = ((1.0 - alpha_m) * m_pred[0] + alpha_m * m_d[0], (1.0 - alpha_m) * m_pred[1] + alpha_m * m_d[1],
                  (1.0 - alpha_m) * m_pred[2] + alpha_m * m_d[2])
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


@njit(cache=False)
def run_batch_predicted(step, state, params, gyr, acc, mag, dt, pred, quat_out, diag_out):
    """``run_batch`` with one prediction row per sample."""
    for i in range(gyr.shape[0]):
        step(state, params, gyr[i], acc[i], mag[i], dt[i], pred[i], diag_out[i])
        quat_out[i, 0] = state[0]
        quat_out[i, 1] = state[1]
        quat_out[i, 2] = state[2]
        quat_out[i, 3] = state[3]


class TogglingFilter(OrientationFilter):
    """The toggling-gain CF driven by per-sample predictions.

    ``update_batch(gyr, acc, mag, predictions=P)`` with ``P (N, S + 6)``: state
    probabilities then η̂_a, η̂_m (sensor frame, m/s² and µT). ``predictions=None`` means
    "no model": the first state with zero noise (useful only for tests).
    """

    name = "toggling"
    Settings = TogglingSettings
    state_names = _STATE
    diagnostic_names = ("alpha_acc", "alpha_mag", "p_static", "bias_norm")

    def _coefficients(self) -> np.ndarray:
        s = self.settings
        return np.array([len(s.states), *s.alpha_acc, *s.alpha_mag, s.gamma, s.bias_gain,
                         s.states.index(s.static_state), s.bias_gate, s.mag_disturbance_scale,
                         s.noise_weight_acc, s.noise_weight_mag], dtype=np.float64)

    @property
    def n_predictions(self) -> int:
        return len(self.settings.states) + N_PRED_NOISE

    def _default_pred(self, n):
        pred = np.zeros((n, self.n_predictions))
        pred[:, 0] = 1.0
        return pred

    def update(self, gyr, acc, mag=None, dt=None, prediction=None) -> np.ndarray:
        pred = self._default_pred(1)[0] if prediction is None else np.asarray(prediction, np.float64)
        if pred.shape != (self.n_predictions,):
            raise ValueError(f"prediction: expected shape ({self.n_predictions},), got {pred.shape}")
        g, a, m, dt_arr = self._inputs(np.reshape(gyr, (1, 3)), np.reshape(acc, (1, 3)),
                                       None if mag is None else np.reshape(mag, (1, 3)), dt)
        toggle_step(self.state, self.params, g[0], a[0], m[0], dt_arr[0], pred, self._diag)
        return self.quat

    def update_batch(self, gyr, acc, mag=None, dt=None, predictions=None):
        from .base import FilterOutput

        g, a, m, dt_arr = self._inputs(gyr, acc, mag, dt)
        n = g.shape[0]
        pred = self._default_pred(n) if predictions is None else np.ascontiguousarray(predictions, np.float64)
        if pred.shape != (n, self.n_predictions):
            raise ValueError(f"predictions: expected shape ({n}, {self.n_predictions}), got {pred.shape}")
        quat_out = np.empty((n, 4))
        diag_out = np.zeros((n, len(self.diagnostic_names)))
        run_batch_predicted(toggle_step, self.state, self.params, g, a, m, dt_arr, pred, quat_out, diag_out)
        if n:
            self._diag[:] = diag_out[-1]
        return FilterOutput(quat_out, {k: diag_out[:, i] for i, k in enumerate(self.diagnostic_names)})


# ------------------------------------------------------------------------------------------------
# Models inside the loop: features pushed every sample, trees evaluated every hop, all compiled.
# ------------------------------------------------------------------------------------------------

from ..streaming_features import N_AUX, N_FEATURES, StreamingFeatures, push_sample, window_features  # noqa: E402
from ..trees import FlatForest, predict_margin_row, softmax  # noqa: E402


class CompiledModels:
    """A trained model bundle as one flat forest: outputs = class margins (softmax applied in the
    loop), then η̂_a x/y/z, then η̂_m x/y/z; plus the feature settings it was trained with."""

    def __init__(self, forest: FlatForest, class_names, feature_settings, schema_hash: str):
        self.forest = forest
        self.class_names = tuple(class_names)
        self.feature_settings = feature_settings
        self.schema_hash = schema_hash
        # the class in which the gyro bias is learned: the model's rest class
        self.static_state = next((c for c in ("rest", "static") if c in self.class_names), self.class_names[0])
        if forest.n_outputs != len(self.class_names) + N_PRED_NOISE:
            raise ValueError(f"forest has {forest.n_outputs} outputs, expected {len(self.class_names)} classes + 6")

    @classmethod
    def from_bundle(cls, bundle) -> "CompiledModels":
        from ..features import FeatureSettings, feature_schema

        settings = FeatureSettings.from_dict({k: v for k, v in bundle.schema.settings.items() if k != "gravity"})
        feature_schema(settings).check(bundle.schema, "streaming features")  # same definitions as training
        forests = [FlatForest.from_booster(bundle.classifier.booster_)]
        for target in ("acc", "mag"):
            forests += [FlatForest.from_booster(b) for b in bundle.regressors[target].boosters_]
        return cls(FlatForest.concatenate(forests), bundle.classifier.class_names_, settings, bundle.schema.hash)

    def predict_samples(self, gyr, acc, mag, fs: float) -> np.ndarray:
        """Per-sample predictions ``(N, S + 6)`` as the in-loop filter holds them: from the
        vectorised features at each window end, held until the next one; NaN before the
        first full window. For learning gains on whole trials without re-running the trees."""
        from ..features import compute_features

        n = np.shape(gyr)[0]
        if n < window_length_samples(fs, self.feature_settings):
            return np.full((n, self.forest.n_outputs), np.nan)
        X, ends = compute_features(gyr, acc, mag, fs, self.feature_settings)
        return hold_predictions(ends, self.predict_windows(X), n)

    def predict_windows(self, X) -> np.ndarray:
        """Prediction rows ``(n, S + 6)`` (class probabilities, η̂_a, η̂_m) of feature rows ``X``."""
        m = self.forest.predict_margin(X)
        k = len(self.class_names)
        m[:, :k] = softmax(m[:, :k])
        return m


def hold_predictions(ends, values, n: int) -> np.ndarray:
    """Per-sample predictions ``(n, k)``: the row of the last window end ``<= sample`` (as the
    in-loop filter holds them between hops); NaN before the first window end."""
    ends = np.asarray(ends)
    order = np.argsort(ends, kind="stable")
    ends, values = ends[order], np.asarray(values)[order]
    pred = np.full((n, values.shape[1]), np.nan)
    idx = np.searchsorted(ends, np.arange(n), side="right") - 1
    pred[idx >= 0] = values[idx[idx >= 0]]
    return pred


def window_length_samples(fs, feature_settings) -> int:
    from ..features import window_length

    return window_length(fs, feature_settings.window_s)


@njit(cache=True)
def inloop_step(state, params, gyr, acc, mag, dt, diag, ring, aux, fparams, last_src, hop, n_classes,
                feature, threshold, left, right, default_left, value, roots, tree_group, base_margin,
                feat, margin, pred):
    """One sample with the models in the loop: push features; at a window end (every ``hop``
    samples once the window is full) evaluate the trees into ``pred`` (held until the next
    hop); then the toggling step."""
    push_sample(ring, aux, fparams, last_src, gyr, acc, mag)
    L = ring.shape[0]
    count = int(aux[0])
    if count >= L and (count - L) % hop == 0:
        window_features(ring, aux, feat)
        predict_margin_row(feat, feature, threshold, left, right, default_left, value, roots, tree_group,
                           base_margin, margin)
        mx = margin[0]
        for s in range(1, n_classes):
            mx = max(mx, margin[s])
        tot = 0.0
        for s in range(n_classes):
            pred[s] = math.exp(margin[s] - mx)  # softmax of the class margins
            tot += pred[s]
        for s in range(n_classes):
            pred[s] /= tot
        for j in range(N_PRED_NOISE):
            pred[n_classes + j] = margin[n_classes + j]
    toggle_step(state, params, gyr, acc, mag, dt, pred, diag)


@njit(cache=True)
def inloop_batch(state, params, gyr, acc, mag, dt, ring, aux, fparams, last_src, hop, n_classes,
                 feature, threshold, left, right, default_left, value, roots, tree_group, base_margin,
                 feat, margin, pred, quat_out, diag_out, pred_out):
    for i in range(gyr.shape[0]):
        inloop_step(state, params, gyr[i], acc[i], mag[i], dt[i], diag_out[i], ring, aux, fparams, last_src, hop,
                    n_classes, feature, threshold, left, right, default_left, value, roots, tree_group, base_margin,
                    feat, margin, pred)
        quat_out[i, 0] = state[0]
        quat_out[i, 1] = state[1]
        quat_out[i, 2] = state[2]
        quat_out[i, 3] = state[3]
        pred_out[i] = pred


class ModelTogglingFilter(TogglingFilter):
    """The toggling CF with its models in the compiled loop: ``ModelTogglingFilter(fs,
    models=CompiledModels.from_bundle(load_bundle(dir)), alpha_acc=..., ...)``.

    ``update``/``update_batch`` take only IMU samples; the diagnostics add the predictions
    (``p_<state>``, ``eta_acc_x`` ...). The full state (filter + feature window + held
    prediction) is saved and restored by ``get_state``/``set_state``.
    """

    def __init__(self, fs: float, settings=None, *, models: CompiledModels, use_mag: bool = True, **overrides):
        if settings is None:
            overrides.setdefault("states", models.class_names)
            overrides.setdefault("static_state", models.static_state)
        super().__init__(fs, settings, use_mag=use_mag, **overrides)
        if tuple(self.settings.states) != models.class_names:
            raise ValueError(f"filter states {self.settings.states} differ from the model's classes {models.class_names}")
        self.models = models
        k = len(models.class_names)
        s = self.settings
        # η̂_m enters step 3 (weight w_m) and step 4 (σ_m > 0), and only in 9D
        mag_needed = self.use_mag and (s.noise_weight_mag > 0.0 or s.mag_disturbance_scale > 0.0)
        unused = [k + j for j in range(3) if s.noise_weight_acc == 0.0] + [k + 3 + j for j in range(3) if not mag_needed]
        # the trees this filter walks: those of outputs it never uses are dropped (same result, less time)
        self.forest = models.forest.without_outputs(unused) if unused else models.forest
        self._features = StreamingFeatures(self.fs, models.feature_settings)
        from ..features import hop_length
        self.hop = hop_length(self.fs, models.feature_settings.hop_s)
        self._reset_model_state()

    def _reset_model_state(self):
        self._features.ring[:] = 0.0
        self._features.aux[:] = 0.0
        self.pred = np.full(self.n_predictions, np.nan)  # no prediction before the first full window
        self._feat = np.empty(N_FEATURES)
        self._margin = np.empty(self.n_predictions)

    def reset(self):
        super().reset()
        if hasattr(self, "models"):
            self._reset_model_state()

    def get_state(self) -> np.ndarray:
        return np.concatenate([self.state, self._features.aux, self._features.ring.ravel(), self.pred])

    def set_state(self, state):
        state = np.asarray(state, np.float64)
        sizes = [self.state.size, N_AUX, self._features.ring.size, self.pred.size]
        if state.shape != (sum(sizes),):
            raise ValueError(f"{type(self).__name__}: state must have shape ({sum(sizes)},), got {state.shape}")
        a, b, c = np.cumsum(sizes)[:3]
        self.state[:] = state[:a]
        self._features.aux[:] = state[a:b]
        self._features.ring[:] = state[b:c].reshape(self._features.ring.shape)
        self.pred[:] = state[c:]

    def _model_args(self):
        return (self._features.ring, self._features.aux, self._features.params, self._features.last_src, self.hop,
                len(self.models.class_names), *self.forest.arrays(), self._feat, self._margin, self.pred)

    def update(self, gyr, acc, mag=None, dt=None, prediction=None) -> np.ndarray:
        if prediction is not None:
            raise ValueError("ModelTogglingFilter predicts itself; use TogglingFilter to pass predictions")
        g, a, m, dt_arr = self._inputs(np.reshape(gyr, (1, 3)), np.reshape(acc, (1, 3)),
                                       None if mag is None else np.reshape(mag, (1, 3)), dt)
        inloop_step(self.state, self.params, g[0], a[0], m[0], dt_arr[0], self._diag, *self._model_args())
        return self.quat

    def update_batch(self, gyr, acc, mag=None, dt=None, predictions=None):
        from .base import FilterOutput

        if predictions is not None:
            raise ValueError("ModelTogglingFilter predicts itself; use TogglingFilter to pass predictions")
        g, a, m, dt_arr = self._inputs(gyr, acc, mag, dt)
        n = g.shape[0]
        quat_out = np.empty((n, 4))
        diag_out = np.zeros((n, len(self.diagnostic_names)))
        pred_out = np.empty((n, self.n_predictions))
        inloop_batch(self.state, self.params, g, a, m, dt_arr, *self._model_args(), quat_out, diag_out, pred_out)
        if n:
            self._diag[:] = diag_out[-1]
        diags = {k: diag_out[:, i] for i, k in enumerate(self.diagnostic_names)}
        names = [f"p_{s}" for s in self.models.class_names] + [f"eta_{t}_{ax}" for t in ("acc", "mag") for ax in "xyz"]
        diags.update({k: pred_out[:, i] for i, k in enumerate(names)})
        return FilterOutput(quat_out, diags)


_COMPILED_CACHE: dict = {}


def load_toggling_filter(model_dir, fs: float, use_mag: bool = True) -> ModelTogglingFilter:
    """The trained toggling filter of a model directory (``togglecf train`` output): the
    models (schema-checked, hash-verified) compiled for the loop, with the learned gains."""
    from pathlib import Path

    from ..gains import load_gains
    from ..models import load_bundle

    key = str(Path(model_dir).resolve())
    if key not in _COMPILED_CACHE:  # flattening the trees takes ~1 s: once per process
        _COMPILED_CACHE[key] = CompiledModels.from_bundle(load_bundle(model_dir))
    models = _COMPILED_CACHE[key]
    return ModelTogglingFilter(fs, load_gains(model_dir, use_mag=use_mag), models=models, use_mag=use_mag)
