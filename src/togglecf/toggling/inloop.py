"""The learned filters with their models in the compiled loop: features pushed every sample, trees
evaluated every hop, the filter's prediction-driven step (``filters.toggling``, ``filters.vqf_toggling``)
after each sample.

A learned filter *holds* two parts: ``filter``, the prediction-driven filter (``TogglingFilter`` or
``VQFTogglingFilter``: settings, coefficients, state, step), and ``predictor``, an ``InLoopPredictor``
(the compiled models, the streaming feature window and the prediction held between hops). Its
``update_batch`` calls the batch kernel of its filter by name: ``toggling_inloop_batch`` runs
``toggle_step``, ``vqf_toggling_inloop_batch`` runs ``vqf_toggling_step``; both are ``run_inloop``
(the loop, inlined) with that step.

The kernels take named records (``NamedTuple``, compiled to structs): the IMU ``Samples``, the
``FeatureWindow``, the ``ModelArrays`` (prediction layout, the trees in both layouts and which one
``walk_forest`` walks, training ranges), the ``HeldPrediction`` (the row held between hops and the
hop's scratch) and the ``Outputs``. They take no function argument, so numba caches them on disk
like the filters' own steps instead of compiling them again in every process (a function passed as
an argument, or closed over, is not cached). numba keys a kernel's cache on its own file only; the
package keys the cache directory on every source file (``togglecf.__init__``), so editing a filter's
step in another file compiles the kernels again.
"""
from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
from numba import njit

from togglecf.features.streaming import N_AUX, N_FEATURES, StreamingFeatures, push_sample, window_features
from togglecf.features.windows import hop_length
from togglecf.filters.base import FilterOutput
from togglecf.filters.prediction import PredictionLayout
from togglecf.filters.toggling import TogglingFilter, toggle_step
from togglecf.filters.vqf_toggling import VQFTogglingFilter, vqf_toggling_step
from togglecf.learn.compiled import CompiledModels
from togglecf.learn.ranges import window_out_of_range
from togglecf.learn.trees import (CompleteForestArrays, FlatForestArrays, predict_margin_row,
                                  predict_margin_row_complete)

__all__ = ["FeatureWindow", "HeldPrediction", "InLoopFilter", "InLoopPredictor", "ModelArrays",
           "ModelTogglingFilter", "ModelVQFTogglingFilter", "Outputs", "Samples", "hop_predict", "prediction_filter",
           "run_inloop", "toggling_inloop_batch", "vqf_toggling_inloop_batch", "walk_forest"]


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
    # the trees, one output per row entry (class margins, η̂_a, η̂_m), in two layouts of learn.trees; walk_forest
    # walks the complete one (predict_margin_row_complete, faster) unless the trees are too deep for it
    complete: CompleteForestArrays  # no trees when walk_complete is False
    flat: FlatForestArrays
    walk_complete: bool
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


@njit(cache=True, inline="always")
def walk_forest(models, feat, margin):
    """The trees' margins of the feature row ``feat`` into ``margin``: the complete layout's walk when
    ``models.walk_complete``, else the flat one (the same margins; ``ModelArrays``)."""
    if models.walk_complete:
        predict_margin_row_complete(feat, models.complete, margin)
    else:
        predict_margin_row(feat, models.flat, margin)


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
    walk_forest(models, feat, margin)
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


@njit(cache=True, inline="always")
def run_inloop(step, state, params, samples, window, models, held, out):
    """The models in the loop, per sample: push the features (``push_sample``); at a window end (every
    ``window.hop`` samples once the window is full) ``hop_predict`` updates ``held`` (the prediction is
    held until the next hop); then ``step`` (a filter's prediction-driven step) with that prediction.
    Inlined into each filter's batch kernel (``toggling_inloop_batch``, ``vqf_toggling_inloop_batch``),
    which names its step. Written for speed: a call per sample with many arguments, the arrays among
    them reference-counted, costs as much as the whole VQF core; the samples go to ``push_sample`` and
    the step as tuples and the step writes a scratch ``diag`` (not row views of the input arrays, each
    reference-counted); the held prediction goes into its rows of ``out`` once a hop (``_hold_rows``), not
    every sample; ``params`` as from ``PredictionDrivenFilter.step_params``."""
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
    filled = 0
    for i in range(gyr.shape[0]):
        g = (gyr[i, 0], gyr[i, 1], gyr[i, 2])
        a = (acc[i, 0], acc[i, 1], acc[i, 2])
        m = (mag[i, 0], mag[i, 1], mag[i, 2])
        push_sample(window.ring, window.aux, window.params, window.last_src, g, a, m)
        if done + i + 1 == next_end:
            _hold_rows(out, filled, i, pred, held.fallback[0])
            filled = i
            next_end += hop
            hop_predict(window, models, held)
        for j in range(diag.shape[0]):
            diag[j] = 0.0  # as a fresh row of diag_out: a step need not write every entry
        step(state, params, g, a, m, dt[i], pred, diag)
        for j in range(diag.shape[0]):
            diag_out[i, j] = diag[j]
        out.quat[i, 0] = state[0]
        out.quat[i, 1] = state[1]
        out.quat[i, 2] = state[2]
        out.quat[i, 3] = state[3]
    _hold_rows(out, filled, gyr.shape[0], pred, held.fallback[0])


@njit(cache=True, inline="always")
def _hold_rows(out, start, stop, pred, fallback):
    """Rows ``start`` to ``stop`` − 1 of ``out.pred`` and ``out.fallback``: the prediction held over them."""
    for i in range(start, stop):
        for j in range(pred.shape[0]):
            out.pred[i, j] = pred[j]
        out.fallback[i] = fallback


@njit(cache=True)
def toggling_inloop_batch(state, params, samples, window, models, held, out):
    """``run_inloop`` with the toggling CF's step, ``filters.toggling.toggle_step``: ``state`` the
    ``TogglingFilter``'s ``(5 + 9,)``, ``params`` its ``step_params()``."""
    run_inloop(toggle_step, state, params, samples, window, models, held, out)


@njit(cache=True)
def vqf_toggling_inloop_batch(state, params, samples, window, models, held, out):
    """``run_inloop`` with the learned VQF's step, ``filters.vqf_toggling.vqf_toggling_step``: ``state``
    the ``VQFTogglingFilter``'s, ``params`` its ``step_params()``."""
    run_inloop(vqf_toggling_step, state, params, samples, window, models, held, out)


#: ``ModelArrays.complete`` for trees walked flat: the complete layout of no trees (the dtypes of
#: ``CompleteForest.arrays``)
_NO_COMPLETE_TREES = CompleteForestArrays(np.zeros(2, np.float32), np.empty(0, np.int32), np.empty(0, np.float32),
                                          np.empty(0, np.float32), np.empty(0, np.int32), np.empty(0, np.int32),
                                          np.empty(0, np.int32), np.empty(0, np.int32), np.empty(0))


class InLoopPredictor:
    """The compiled models of a learned filter as its loop runs them: the streaming feature window
    (pushed every sample), the trees (walked at each window end, ``hop`` samples apart) and the
    prediction row held between window ends.

    Attributes:
        models: the ``CompiledModels``.
        streaming_features: the feature window (``StreamingFeatures``: its settings, window length
            ``L`` and per-sample constants ``params``, e.g. for the C export).
        hop: samples from one window end to the next.
        window, held: the ``FeatureWindow`` and ``HeldPrediction`` records the kernel updates in place.
        pred: the held row ``(S + 6,)`` (NaN before the first full window); fallback: ``(1,)``, 1.0
            while the held window was out of the training range (``learn.ranges``).
    """

    def __init__(self, fs: float, models: CompiledModels, layout: PredictionLayout, unused_outputs=()):
        """``layout``: the filter's prediction row; ``unused_outputs``: row indices the filter never
        uses, whose trees are not walked (the same result in less time)."""
        self.models = models
        self.layout = layout
        self.forest = models.forest.without_outputs(unused_outputs) if unused_outputs else models.forest
        self.streaming_features = StreamingFeatures(fs, models.feature_settings)
        self.hop = hop_length(fs, models.feature_settings.hop_s)
        f = self.streaming_features
        self.window = FeatureWindow(f.ring, f.aux, f.params, f.last_src, self.hop)
        self.reset()

    @property
    def forest(self):
        """The ``FlatForest`` walked (set: also lays it out for the loop, ``arrays``)."""
        return self._forest

    @forest.setter
    def forest(self, forest):
        self._forest = forest
        try:  # the same trees laid out to walk faster (identical margins); very deep trees keep the plain walk
            complete, walk_complete = forest.complete().arrays(), True
        except ValueError:
            complete, walk_complete = _NO_COMPLETE_TREES, False
        m = self.models
        self.arrays = ModelArrays(self.layout, complete, forest.arrays(), walk_complete, m.feature_low, m.feature_high,
                                  m.max_out_of_range)

    def reset(self):
        """An empty feature window and no prediction held."""
        self.streaming_features.ring[:] = 0.0
        self.streaming_features.aux[:] = 0.0
        self.pred = np.full(self.layout.size, np.nan)  # no prediction before the first full window
        self.fallback = np.zeros(1)
        self.held = HeldPrediction(self.pred, self.fallback, np.empty(N_FEATURES), np.empty(self.layout.size))

    def get_state(self) -> np.ndarray:
        """The window's running sums ``(N_AUX,)``, its samples (ring, flattened), the held row and
        the fallback flag, concatenated."""
        f = self.streaming_features
        return np.concatenate([f.aux, f.ring.ravel(), self.pred, self.fallback])

    def set_state(self, state):
        """Restore what ``get_state`` returned (shape checked by the caller)."""
        f = self.streaming_features
        a, b, c = np.cumsum([N_AUX, f.ring.size, self.pred.size])
        f.aux[:] = state[:a]
        f.ring[:] = state[a:b].reshape(f.ring.shape)
        self.pred[:] = state[b:c]
        self.fallback[:] = state[c:]

    @property
    def state_size(self) -> int:
        return N_AUX + self.streaming_features.ring.size + self.pred.size + 1


def prediction_filter(filter_cls, fs: float, settings, models: CompiledModels, use_mag: bool, overrides: dict):
    """``filter_cls(fs, settings, use_mag=use_mag, **overrides)`` for ``models``: with no ``settings``,
    those of ``filter_cls.settings_for`` the model's classes (``overrides`` included). Refuses settings
    whose states are not the model's classes."""
    if settings is None:
        settings, overrides = filter_cls.settings_for(models.class_names, models.static_state, **overrides), {}
    filt = filter_cls(fs, settings, use_mag=use_mag, **overrides)
    if tuple(filt.settings.states) != models.class_names:
        raise ValueError(f"filter states {filt.settings.states} differ from the model's classes {models.class_names}")
    return filt


class InLoopFilter:
    """A prediction-driven filter (``filter``: ``TogglingFilter`` or ``VQFTogglingFilter``) and the
    models that predict for it (``predictor``: an ``InLoopPredictor``), run sample by sample in one
    compiled loop. A subclass's ``update_batch`` names the loop of its filter's step.

    ``update``/``update_batch`` take only IMU samples; the diagnostics are the filter's, plus the
    predictions (``p_<state>``, ``eta_acc_x`` ...) and ``fallback`` (1 while the held window was out
    of the training range, ``learn.ranges``). ``get_state``/``set_state`` save and restore the full
    state: the filter's ``(n,)``, then the predictor's (feature window, held prediction, fallback flag).
    The filter's settings, coefficients and state are read through (``settings``, ``params``,
    ``state``, ``quat`` ...).
    """

    def __init__(self, filt, models: CompiledModels):
        s, layout = filt.settings, filt.layout
        # η̂_m enters the noise removal (weight w_m) and the disturbance back-off (σ_m > 0), in 9D only; the class
        # probabilities whatever a filter's per-state values make of them (none: the classifier's trees are not
        # walked, its outputs stay at their base margins, a constant prior)
        mag_needed = filt.use_mag and (s.noise_weight_mag > 0.0 or s.mag_disturbance_scale > 0.0)
        unused = ((layout.outputs(layout.probabilities) if not filt.uses_class_probabilities else [])
                  + (layout.outputs(layout.eta_acc) if s.noise_weight_acc == 0.0 else [])
                  + (layout.outputs(layout.eta_mag) if not mag_needed else []))
        self.filter = filt
        self.predictor = InLoopPredictor(filt.fs, models, layout, unused)
        self._diag = np.zeros(len(filt.diagnostic_names))  # the last sample's, for last_diagnostics

    def __repr__(self):
        classes = self.models.class_names
        return f"{type(self).__name__}(filter={self.filter!r}, models: classes {classes}, hop {self.hop})"

    # -- the held filter, read through ---------------------------------------------------------
    name = property(lambda self: self.filter.name)
    fs = property(lambda self: self.filter.fs)
    Ts = property(lambda self: self.filter.Ts)
    use_mag = property(lambda self: self.filter.use_mag)
    settings = property(lambda self: self.filter.settings)
    params = property(lambda self: self.filter.params)
    state = property(lambda self: self.filter.state)
    state_names = property(lambda self: self.filter.state_names)
    diagnostic_names = property(lambda self: self.filter.diagnostic_names)
    layout = property(lambda self: self.filter.layout)
    n_predictions = property(lambda self: self.filter.n_predictions)
    quat = property(lambda self: self.filter.quat)

    def state_dict(self) -> dict:
        """The filter's state by name (``OrientationFilter.state_dict``)."""
        return self.filter.state_dict()

    def set_quat(self, q):
        """Set the filter's orientation (``OrientationFilter.set_quat``)."""
        self.filter.set_quat(q)

    @property
    def last_diagnostics(self) -> dict:
        return dict(zip(self.diagnostic_names, self._diag.tolist()))

    # -- the held predictor, read through ------------------------------------------------------
    models = property(lambda self: self.predictor.models)
    streaming_features = property(lambda self: self.predictor.streaming_features)
    hop = property(lambda self: self.predictor.hop)

    @property
    def forest(self):
        """The ``FlatForest`` the predictor walks (``InLoopPredictor.forest``; settable)."""
        return self.predictor.forest

    @forest.setter
    def forest(self, forest):
        self.predictor.forest = forest

    # -- state -----------------------------------------------------------------------------------
    def reset(self):
        """Forget everything: the filter's state, the feature window and the held prediction."""
        self.filter.reset()
        self.predictor.reset()

    def get_state(self) -> np.ndarray:
        return np.concatenate([self.filter.state, self.predictor.get_state()])

    def set_state(self, state):
        state = np.asarray(state, np.float64)
        n = self.filter.state.size
        if state.shape != (n + self.predictor.state_size,):
            raise ValueError(f"{type(self).__name__}: state must have shape ({n + self.predictor.state_size},), "
                             f"got {state.shape}")
        self.filter.state[:] = state[:n]
        self.predictor.set_state(state[n:])

    # -- running ---------------------------------------------------------------------------------
    def update(self, gyr, acc, mag=None, dt=None, prediction=None) -> np.ndarray:
        """One sample (``OrientationFilter.update``): ``update_batch`` of one row, the same kernel."""
        if prediction is not None:
            raise ValueError(f"{type(self).__name__} predicts itself; pass predictions to the filter without models")
        self.update_batch(np.reshape(gyr, (1, 3)), np.reshape(acc, (1, 3)),
                          None if mag is None else np.reshape(mag, (1, 3)), None if dt is None else float(dt))
        return self.quat

    def batch_records(self, gyr, acc, mag, dt, predictions) -> tuple[Samples, Outputs]:
        """The kernel's ``Samples`` (validated by the filter, ``OrientationFilter.batch_inputs``) and
        fresh ``Outputs`` for them."""
        if predictions is not None:
            raise ValueError(f"{type(self).__name__} predicts itself; pass predictions to the filter without models")
        samples = Samples(*self.filter.batch_inputs(gyr, acc, mag, dt))
        n, n_pred = samples.gyr.shape[0], self.predictor.layout.size
        return samples, Outputs(np.empty((n, 4)), np.zeros((n, len(self.diagnostic_names))), np.empty((n, n_pred)),
                                np.empty(n))

    def batch_output(self, out: Outputs) -> FilterOutput:
        """The ``FilterOutput`` of a batch the kernel wrote into ``out``."""
        if out.quat.shape[0]:
            self._diag[:] = out.diag[-1]
        diags = {k: out.diag[:, i] for i, k in enumerate(self.diagnostic_names)}
        diags.update({k: out.pred[:, i] for i, k in enumerate(self.layout.names(self.models.class_names))})
        diags["fallback"] = out.fallback
        return FilterOutput(out.quat, diags)


class ModelTogglingFilter(InLoopFilter):
    """The toggling CF (``filters.toggling``) with its models in the compiled loop, e.g.
    ``ModelTogglingFilter(fs, settings, models=CompiledModels.from_bundle(load_bundle(dir)))``; with no
    ``settings``, ``TogglingFilter.settings_for`` the model's classes (``overrides`` replace fields)."""

    def __init__(self, fs: float, settings=None, *, models: CompiledModels, use_mag: bool = True, **overrides):
        super().__init__(prediction_filter(TogglingFilter, fs, settings, models, use_mag, overrides), models)

    def update_batch(self, gyr, acc, mag=None, dt=None, predictions=None) -> FilterOutput:
        samples, out = self.batch_records(gyr, acc, mag, dt, predictions)
        p = self.predictor
        toggling_inloop_batch(self.filter.state, self.filter.step_params(), samples, p.window, p.arrays, p.held, out)
        return self.batch_output(out)


class ModelVQFTogglingFilter(InLoopFilter):
    """The VQF core with learned time constants (``filters.vqf_toggling``) with its models in the
    compiled loop; with no ``settings``, ``VQFTogglingFilter.settings_for`` the model's classes."""

    def __init__(self, fs: float, settings=None, *, models: CompiledModels, use_mag: bool = True, **overrides):
        super().__init__(prediction_filter(VQFTogglingFilter, fs, settings, models, use_mag, overrides), models)

    def update_batch(self, gyr, acc, mag=None, dt=None, predictions=None) -> FilterOutput:
        samples, out = self.batch_records(gyr, acc, mag, dt, predictions)
        p = self.predictor
        vqf_toggling_inloop_batch(self.filter.state, self.filter.step_params(), samples, p.window, p.arrays, p.held,
                                  out)
        return self.batch_output(out)
