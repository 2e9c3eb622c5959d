"""The learned filters with their models in the compiled loop: features pushed every sample, trees
evaluated every hop, the filter's prediction-driven step (``filters.toggling``, ``filters.vqf_toggling``)
after each sample.

The kernel ``inloop_batch(state, params, samples, window, models, held, out)`` takes named records
(``NamedTuple``, compiled to structs): the IMU ``Samples``, the ``FeatureWindow``, the ``ModelArrays``
(prediction layout, trees, training ranges), the ``HeldPrediction`` (the row held between hops and the
hop's scratch) and the ``Outputs``. It takes no function: which filter step and which tree walk run is
decided by the types of ``params`` and of the forest record when numba compiles it (``filter_step``,
``walk_forest``), so the kernel is cached on disk like the filters' own steps instead of being compiled
again in every process. As every numba cache, it is keyed on this file's source: after editing a
filter's step in another file, clear the cache (``__pycache__``) or the old step may run on.
"""
from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
from numba import njit, types
from numba.extending import overload

from togglecf.features.streaming import N_AUX, N_FEATURES, StreamingFeatures, push_sample, window_features
from togglecf.features.windows import hop_length
from togglecf.filters.base import FilterOutput
from togglecf.filters.prediction import PredictionLayout
from togglecf.filters.toggling import TogglingFilter, prediction_step_of
from togglecf.filters.vqf_toggling import VQFTogglingFilter
from togglecf.learn.compiled import CompiledModels
from togglecf.learn.ranges import window_out_of_range
from togglecf.learn.trees import (CompleteForestArrays, FlatForestArrays, predict_margin_row,
                                  predict_margin_row_complete)

__all__ = ["FeatureWindow", "HeldPrediction", "InLoopModels", "ModelArrays",
           "ModelTogglingFilter", "ModelVQFTogglingFilter", "Outputs", "Samples", "filter_step", "hop_predict",
           "inloop_batch", "walk_forest"]


class Samples(NamedTuple):
    """The IMU samples of one batch: ``gyr`` [rad/s], ``acc`` [m/s²], ``mag`` [µT] ``(N, 3)``, ``dt`` [s] ``(N,)``."""

    gyr: np.ndarray
    acc: np.ndarray
    mag: np.ndarray
    dt: np.ndarray


class FeatureWindow(NamedTuple):
    """The streaming feature window (``features.streaming.StreamingFeatures``), updated in place."""

    ring: np.ndarray  # (L, channels) the window's samples
    aux: np.ndarray  # (N_AUX,) its running sums; aux[0] the samples pushed so far
    params: tuple  # the window's per-sample constants (FeatureCoefficients)
    last_src: np.ndarray  # channel sources of the last-sample features
    hop: int  # samples from one window end to the next


class ModelArrays(NamedTuple):
    """The models as the loop uses them."""

    layout: PredictionLayout  # of the prediction row (filters.prediction)
    # learn.trees' CompleteForestArrays (walked by predict_margin_row_complete) or FlatForestArrays (very deep
    # trees: predict_margin_row): one output per row entry (class margins, η̂_a, η̂_m)
    forest: tuple
    low: np.ndarray  # (N_FEATURES,) training range of each feature (learn.ranges; NaN: unbounded)
    high: np.ndarray
    max_out_of_range: float  # the largest fraction of bounded features out of range that still predicts


class HeldPrediction(NamedTuple):
    """The prediction held between window ends, and the scratch of a window end (arrays, in place)."""

    pred: np.ndarray  # (S + 6,) the row the filter step gets; NaN before the first full window
    fallback: np.ndarray  # (1,) 1.0 while the held window was out of the training range
    feat: np.ndarray  # (N_FEATURES,) scratch: the window's features
    margin: np.ndarray  # (S + 6,) scratch: the trees' margins


class Outputs(NamedTuple):
    """Per-sample outputs of one batch: ``quat (N, 4)``, ``diag (N, D)``, ``pred (N, S + 6)``, ``fallback (N,)``."""

    quat: np.ndarray
    diag: np.ndarray
    pred: np.ndarray
    fallback: np.ndarray


def walk_forest(forest, feat, margin):
    """The trees' margins of the feature row ``feat`` into ``margin``: compiled code only, the walk
    chosen by the type of ``forest`` (``learn.trees.CompleteForestArrays`` or ``FlatForestArrays``) at
    compile time."""
    raise TypeError("walk_forest runs in compiled code only")


@overload(walk_forest, inline="always")
def _walk_forest_typed(forest, feat, margin):
    if isinstance(forest, types.BaseNamedTuple) and forest.instance_class is CompleteForestArrays:
        return lambda forest, feat, margin: predict_margin_row_complete(feat, forest, margin)
    if isinstance(forest, types.BaseNamedTuple) and forest.instance_class is FlatForestArrays:
        return lambda forest, feat, margin: predict_margin_row(feat, forest, margin)
    return None


def filter_step(state, params, gyr, acc, mag, dt, pred, diag):
    """The prediction-driven step of the filter whose coefficients ``params`` are: compiled code
    only, the step chosen by the type of ``params`` at compile time (``filters.toggling.prediction_step_of``)."""
    raise TypeError("filter_step runs in compiled code only")


@overload(filter_step, inline="always")
def _filter_step_typed(state, params, gyr, acc, mag, dt, pred, diag):
    if not isinstance(params, types.BaseNamedTuple):
        return None
    step = prediction_step_of(params.instance_class)

    def impl(state, params, gyr, acc, mag, dt, pred, diag):
        step(state, params, gyr, acc, mag, dt, pred, diag)
    return impl


@njit(cache=True)
def hop_predict(window, models, held):
    """At a window end: the window's features, then either ``held.pred`` from the trees (softmax over
    the class margins; η̂ the regressors' margins) and ``held.fallback[0] = 0``, or, when the features
    are out of the training range (``learn.ranges``), ``held.pred`` NaN (no prediction: the filter's
    fallback) and ``held.fallback[0] = 1``."""
    feat, margin, pred, layout = held.feat, held.margin, held.pred, models.layout
    window_features(window.ring, window.aux, feat)
    if window_out_of_range(feat, models.low, models.high, models.max_out_of_range):
        held.fallback[0] = 1.0
        pred[:] = math.nan
        return
    held.fallback[0] = 0.0
    walk_forest(models.forest, feat, margin)
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


@njit(cache=True)
def inloop_batch(state, params, samples, window, models, held, out):
    """The models in the loop, per sample: push the features (``push_sample``); at a window end (every
    ``window.hop`` samples once the window is full) ``hop_predict`` updates ``held`` (the prediction is
    held until the next hop); then the filter's step (``filter_step``) with that prediction. The one
    kernel for ``update`` (one row) and ``update_batch``. Written for speed: a call per sample with
    many arguments, the arrays among them reference-counted, cost as much as the whole VQF core; the
    samples go to ``push_sample`` and the step as tuples and the step writes a scratch ``diag`` (row
    views of the input arrays, each reference-counted, cost 0.1 µs per sample); ``params`` as from
    ``PredictionDrivenFilter.step_params``."""
    L = window.ring.shape[0]
    hop = window.hop
    pred = held.pred
    gyr, acc, mag, dt = samples.gyr, samples.acc, samples.mag, samples.dt
    diag_out = out.diag
    diag = np.zeros(diag_out.shape[1])
    # the sample count after the next window end's push (count >= L and (count - L) % hop == 0, without a
    # division per sample)
    done = int(window.aux[0])
    next_end = L if done < L else L + ((done - L) // hop + 1) * hop
    for i in range(gyr.shape[0]):
        g = (gyr[i, 0], gyr[i, 1], gyr[i, 2])
        a = (acc[i, 0], acc[i, 1], acc[i, 2])
        m = (mag[i, 0], mag[i, 1], mag[i, 2])
        push_sample(window.ring, window.aux, window.params, window.last_src, g, a, m)
        if done + i + 1 == next_end:
            next_end += hop
            hop_predict(window, models, held)
        for j in range(diag.shape[0]):
            diag[j] = 0.0  # as a fresh row of diag_out: a step need not write every entry
        filter_step(state, params, g, a, m, dt[i], pred, diag)
        for j in range(diag.shape[0]):
            diag_out[i, j] = diag[j]
        out.quat[i, 0] = state[0]
        out.quat[i, 1] = state[1]
        out.quat[i, 2] = state[2]
        out.quat[i, 3] = state[3]
        for j in range(pred.shape[0]):
            out.pred[i, j] = pred[j]
        out.fallback[i] = held.fallback[0]


class InLoopModels:
    """Mixin: a ``PredictionDrivenFilter`` with its models in the compiled loop, e.g.
    ``ModelTogglingFilter(fs, settings, models=CompiledModels.from_bundle(load_bundle(dir)))``.

    ``update``/``update_batch`` take only IMU samples; the diagnostics add the predictions
    (``p_<state>``, ``eta_acc_x`` ...) and ``fallback`` (1 while the held window was out of the
    training range, ``learn.ranges``). The full state (filter + feature window + held
    prediction + fallback flag) is saved and restored by ``get_state``/``set_state``.
    """

    def __init__(self, fs: float, settings=None, *, models: CompiledModels, use_mag: bool = True, **overrides):
        if settings is None:  # the model's classes (the filter's settings_for)
            settings, overrides = self.settings_for(models.class_names, models.static_state, **overrides), {}
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
        f = self._features
        self._window = FeatureWindow(f.ring, f.aux, f.params, f.last_src, self.hop)
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
            walk = forest.complete().arrays()
        except ValueError:
            walk = forest.arrays()
        m = self.models
        self._model_arrays = ModelArrays(self.layout, walk, m.feature_low, m.feature_high, m.max_out_of_range)

    def _reset_model_state(self):
        self._features.ring[:] = 0.0
        self._features.aux[:] = 0.0
        self.pred = np.full(self.n_predictions, np.nan)  # no prediction before the first full window
        self.fallback = np.zeros(1)  # 1 while the held window is out of the training range
        self._held = HeldPrediction(self.pred, self.fallback, np.empty(N_FEATURES), np.empty(self.n_predictions))

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
        samples = Samples(*self._inputs(gyr, acc, mag, dt))
        n = samples.gyr.shape[0]
        out = Outputs(np.empty((n, 4)), np.zeros((n, len(self.diagnostic_names))), np.empty((n, self.n_predictions)),
                      np.empty(n))
        inloop_batch(self.state, self.step_params(), samples, self._window, self._model_arrays, self._held, out)
        if n:
            self._diag[:] = out.diag[-1]
        diags = {k: out.diag[:, i] for i, k in enumerate(self.diagnostic_names)}
        diags.update({k: out.pred[:, i] for i, k in enumerate(self.layout.names(self.models.class_names))})
        diags["fallback"] = out.fallback
        return FilterOutput(out.quat, diags)


class ModelTogglingFilter(InLoopModels, TogglingFilter):
    """The toggling CF (``filters.toggling``) with its models in the compiled loop."""


class ModelVQFTogglingFilter(InLoopModels, VQFTogglingFilter):
    """The VQF core with learned time constants (``filters.vqf_toggling``) with its models in the loop."""
