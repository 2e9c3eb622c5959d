"""The toggling filter with its models in the compiled loop: features pushed every sample, trees
evaluated every hop, the toggling step (``filters.toggling``) after each sample."""
from __future__ import annotations

import math
from dataclasses import fields

import numpy as np
from numba import njit

from togglecf.features.streaming import N_AUX, N_FEATURES, StreamingFeatures, push_sample, window_features
from togglecf.features.windows import hop_length
from togglecf.filters.base import FilterOutput
from togglecf.filters.prediction import PredictionLayout
from togglecf.filters.toggling import TogglingFilter
from togglecf.filters.vqf_toggling import VQFTogglingFilter
from togglecf.learn.compiled import CompiledModels
from togglecf.learn.ranges import window_out_of_range
from togglecf.learn.trees import predict_margin_row, predict_margin_row_complete

__all__ = ["InLoopModels", "ModelTogglingFilter", "ModelVQFTogglingFilter", "hop_predict",
           "inloop_batch", "params_by_value"]


# cache=False as filters.base.run_batch: numba cannot cache a function that takes another compiled
# function as an argument (pickling the dispatcher type fails: "underlying object has vanished")
@njit(cache=False)
def hop_predict(ring, aux, layout, predict, forest, feat, margin, pred, low, high, max_out_of_range, fallback):
    """At a window end: the window's features, then either ``pred`` from the trees (``predict(feat,
    *forest, margin)``: ``learn.trees.predict_margin_row_complete`` with ``CompleteForest.arrays()``,
    or ``predict_margin_row`` with ``FlatForest.arrays()``; softmax over the class margins) and
    ``fallback[0] = 0``, or, when the features are out of the training range (``learn.ranges``),
    ``pred`` NaN (no prediction: the filter's default) and ``fallback[0] = 1``."""
    window_features(ring, aux, feat)
    if window_out_of_range(feat, low, high, max_out_of_range):
        fallback[0] = 1.0
        pred[:] = math.nan
        return
    fallback[0] = 0.0
    predict(feat, *forest, margin)
    mx = margin[0]
    for s in range(1, layout.n_states):
        mx = max(mx, margin[s])
    tot = 0.0
    for s in range(layout.n_states):
        pred[s] = math.exp(margin[s] - mx)  # softmax of the class margins
        tot += pred[s]
    for s in range(layout.n_states):
        pred[s] /= tot
    for j in range(layout.eta_acc_index, layout.size):  # η̂_a, η̂_m: the regressors' margins as they are
        pred[j] = margin[j]


@njit(cache=False)
def inloop_batch(step, state, params, gyr, acc, mag, dt, ring, aux, fparams, last_src, hop, layout, predict, forest,
                 feat, margin, pred, low, high, max_out_of_range, fallback, quat_out, diag_out, pred_out, fallback_out):
    """The models in the loop, per sample: push the features (``push_sample``); at a window end (every
    ``hop`` samples once the window is full) ``hop_predict`` updates ``pred`` (held until the next hop)
    and ``fallback``; then the filter's ``step`` with that prediction. The one kernel for ``update``
    (one row) and ``update_batch``: a second, per-sample kernel would be compiled again in every
    process (a function argument keeps numba from caching either). Written for speed: a call per
    sample with some 30 arguments, the arrays among them reference-counted, cost as much as the whole
    VQF core; the samples go to ``push_sample`` and ``step`` as tuples and the step writes a scratch
    ``diag`` (row views of the input arrays, each reference-counted, cost 0.1 µs per sample);
    ``params`` as from ``params_by_value``."""
    L = ring.shape[0]
    diag = np.zeros(diag_out.shape[1])
    # the sample count after the next window end's push (count >= L and (count - L) % hop == 0, without a
    # division per sample)
    done = int(aux[0])
    next_end = L if done < L else L + ((done - L) // hop + 1) * hop
    for i in range(gyr.shape[0]):
        g = (gyr[i, 0], gyr[i, 1], gyr[i, 2])
        a = (acc[i, 0], acc[i, 1], acc[i, 2])
        m = (mag[i, 0], mag[i, 1], mag[i, 2])
        push_sample(ring, aux, fparams, last_src, g, a, m)
        if done + i + 1 == next_end:
            next_end += hop
            hop_predict(ring, aux, layout, predict, forest, feat, margin, pred, low, high, max_out_of_range,
                        fallback)
        for j in range(diag.shape[0]):
            diag[j] = 0.0  # as a fresh row of diag_out: a step need not write every entry
        step(state, params, g, a, m, dt[i], pred, diag)
        for j in range(diag.shape[0]):
            diag_out[i, j] = diag[j]
        quat_out[i, 0] = state[0]
        quat_out[i, 1] = state[1]
        quat_out[i, 2] = state[2]
        quat_out[i, 3] = state[3]
        for j in range(pred.shape[0]):
            pred_out[i, j] = pred[j]
        fallback_out[i] = fallback[0]


def params_by_value(params):
    """``params`` (a coefficients record) with its non-empty 1-D float arrays as tuples of the same
    values: numba reference-counts every array of a record at each call of the filter's step
    (measured 0.08 µs per sample for the five arrays of ``VQFTogglingCoefficients``, a quarter of the
    VQF core), while a tuple of floats is passed as plain values. The steps only index these fields."""
    conv = {k: tuple(float(x) for x in v) for k, v in params._asdict().items()
            if isinstance(v, np.ndarray) and v.ndim == 1 and v.size and v.dtype == np.float64}
    return params._replace(**conv) if conv else params


class InLoopModels:
    """Mixin: a ``PredictionDrivenFilter`` with its models in the compiled loop, e.g.
    ``ModelTogglingFilter(fs, settings, models=CompiledModels.from_bundle(load_bundle(dir)))``.

    ``update``/``update_batch`` take only IMU samples; the diagnostics add the predictions
    (``p_<state>``, ``eta_acc_x`` ...) and ``fallback`` (1 while the held window was out of the
    training range, ``learn.ranges``). The full state (filter + feature window + held
    prediction + fallback flag) is saved and restored by ``get_state``/``set_state``.
    """

    def __init__(self, fs: float, settings=None, *, models: CompiledModels, use_mag: bool = True, **overrides):
        if settings is None:  # the model's classes; built in one go so per-state defaults match their number
            kw = {"states": models.class_names}
            if "static_state" in {f.name for f in fields(self.Settings)}:
                kw["static_state"] = models.static_state
            settings, overrides = self.Settings(**{**kw, **overrides}), {}
        super().__init__(fs, settings, use_mag=use_mag, **overrides)
        if tuple(self.settings.states) != models.class_names:
            raise ValueError(f"filter states {self.settings.states} differ from the model's classes {models.class_names}")
        self.models = models
        s, layout = self.settings, self.layout
        # η̂_m enters the noise removal (weight w_m) and the disturbance back-off (σ_m > 0), in 9D only
        mag_needed = self.use_mag and (s.noise_weight_mag > 0.0 or s.mag_disturbance_scale > 0.0)
        unused = ((layout.outputs(layout.eta_acc) if s.noise_weight_acc == 0.0 else [])
                  + (layout.outputs(layout.eta_mag) if not mag_needed else []))
        # the trees this filter walks: those of outputs it never uses are dropped (same result, less time)
        self.forest = models.forest.without_outputs(unused) if unused else models.forest
        self._features = StreamingFeatures(self.fs, models.feature_settings)
        self.hop = hop_length(self.fs, models.feature_settings.hop_s)
        self._reset_model_state()

    @property
    def streaming_features(self) -> StreamingFeatures:
        """The feature window pushed every sample (its settings, window length ``L`` and
        per-sample constants ``params``, e.g. for the C export)."""
        return self._features

    @property
    def forest(self):
        """The ``FlatForest`` this filter walks (set: also lays it out for the loop)."""
        return self._forest

    @forest.setter
    def forest(self, forest):
        self._forest = forest
        try:  # the same trees laid out to walk faster (identical margins); very deep trees keep the plain walk
            self._predict, self._forest_arrays = predict_margin_row_complete, forest.complete().arrays()
        except ValueError:
            self._predict, self._forest_arrays = predict_margin_row, forest.arrays()

    def _reset_model_state(self):
        self._features.ring[:] = 0.0
        self._features.aux[:] = 0.0
        self.pred = np.full(self.n_predictions, np.nan)  # no prediction before the first full window
        self._feat = np.empty(N_FEATURES)
        self._margin = np.empty(self.n_predictions)
        self.fallback = np.zeros(1)  # 1 while the held window is out of the training range

    def reset(self):
        super().reset()
        if hasattr(self, "models"):
            self._reset_model_state()

    def get_state(self) -> np.ndarray:
        return np.concatenate([self.state, self._features.aux, self._features.ring.ravel(), self.pred, self.fallback])

    def set_state(self, state):
        state = np.asarray(state, np.float64)
        sizes = [self.state.size, N_AUX, self._features.ring.size, self.pred.size, 1]
        if state.shape != (sum(sizes),):
            raise ValueError(f"{type(self).__name__}: state must have shape ({sum(sizes)},), got {state.shape}")
        a, b, c, d = np.cumsum(sizes)[:4]
        self.state[:] = state[:a]
        self._features.aux[:] = state[a:b]
        self._features.ring[:] = state[b:c].reshape(self._features.ring.shape)
        self.pred[:] = state[c:d]
        self.fallback[:] = state[d:]

    def _loop_params(self):
        """``params_by_value(self.params)``, rebuilt when ``self.params`` is replaced."""
        if getattr(self, "_loop_params_of", None) is not self.params:
            self._loop_params_of, self._loop_params_value = self.params, params_by_value(self.params)
        return self._loop_params_value

    def _model_args(self):
        return (self._features.ring, self._features.aux, self._features.params, self._features.last_src, self.hop,
                self.layout, self._predict, self._forest_arrays, self._feat, self._margin, self.pred,
                self.models.feature_low, self.models.feature_high, self.models.max_out_of_range, self.fallback)

    def update(self, gyr, acc, mag=None, dt=None, prediction=None) -> np.ndarray:
        """One sample (``OrientationFilter.update``): ``update_batch`` of one row, the same kernel."""
        if prediction is not None:
            raise ValueError(f"{type(self).__name__} predicts itself; pass predictions to the filter without models")
        self.update_batch(np.reshape(gyr, (1, 3)), np.reshape(acc, (1, 3)),
                          None if mag is None else np.reshape(mag, (1, 3)), None if dt is None else float(dt))
        return self.quat

    def update_batch(self, gyr, acc, mag=None, dt=None, predictions=None):
        if predictions is not None:
            raise ValueError(f"{type(self).__name__} predicts itself; pass predictions to the filter without models")
        g, a, m, dt_arr = self._inputs(gyr, acc, mag, dt)
        n = g.shape[0]
        quat_out = np.empty((n, 4))
        diag_out = np.zeros((n, len(self.diagnostic_names)))
        pred_out = np.empty((n, self.n_predictions))
        fallback_out = np.empty(n)
        inloop_batch(type(self).step, self.state, self._loop_params(), g, a, m, dt_arr, *self._model_args(), quat_out, diag_out,
                     pred_out, fallback_out)
        if n:
            self._diag[:] = diag_out[-1]
        diags = {k: diag_out[:, i] for i, k in enumerate(self.diagnostic_names)}
        names = self.layout.names(self.models.class_names)
        diags.update({k: pred_out[:, i] for i, k in enumerate(names)})
        diags["fallback"] = fallback_out
        return FilterOutput(quat_out, diags)


class ModelTogglingFilter(InLoopModels, TogglingFilter):
    """The toggling CF (``filters.toggling``) with its models in the compiled loop."""


class ModelVQFTogglingFilter(InLoopModels, VQFTogglingFilter):
    """The VQF core with learned time constants (``filters.vqf_toggling``) with its models in the loop."""
