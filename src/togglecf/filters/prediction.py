"""One prediction row and what the two learned filters take from it (``filters.toggling``, the
toggling CF, and ``filters.vqf_toggling``, the learned VQF): the row's layout, the confidence in
its class probabilities, the fallback, the noise removal and the magnetic back-off. Each filter
keeps only its own core (gains or time constants) and calls these. And their common base,
``PredictionDrivenFilter``: a filter whose step takes one such row per sample beside the IMU sample
(``update``/``update_batch`` with given predictions, ``run_batch_predicted``; the models in the loop:
``toggling.inloop``).

Row (``PredictionLayout``): ``[p_1..p_S, η̂_a (3), η̂_m (3)]``: the class probabilities of the S
motion states (any non-negative weights; they need not sum to 1), then the predicted acc noise
η̂_a [m/s²] and mag noise η̂_m [µT] in the sensor frame. NaN probabilities mean "no prediction"
(before the first full window, a window out of the models' training range, a failed model).

1. confidence   the probabilities are *valid* when every p_s is finite and ≥ 0 and Σ_s p_s > 0
                (``class_evidence``); the confidence is c = max_s p_s / Σ_s p_s
2. fallback     what a filter does without a valid prediction, or with a confidence below its
                floor c₀. **The two filters differ here, on purpose, and this is the one place
                where the difference is written:**

                ==================  =================================  ===================================
                                    toggling CF (``switch_status``)    learned VQF (``blend_trust``)
                ==================  =================================  ===================================
                rule                a hard switch: ``LEARNED`` when    a trust λ = clip((c − c₀)/(1 − c₀),
                                    valid and max p ≥ c₀ Σ p, else     0, 1) (0 when not valid) that blends
                                    ``NO_PREDICTION`` /                the learned values towards the
                                    ``LOW_CONFIDENCE``                 core's own (in ln τ)
                falls back to       the cautious gains (per sensor     the core's own settings (learning
                                    the slowest per-state one)         off)
                noise removal and   only on a used prediction          whenever η̂ is finite, whatever
                back-off (3, 4)     (``LEARNED``) with finite η̂        the probabilities
                ==================  =================================  ===================================

                Why: the toggling CF's gains are a function of the probabilities only (a toggle), so
                the unused prediction's η̂ is dropped with it, and the cautious gains are not the
                values of any state; the learned VQF's fallback is a running filter of its own (the
                core), towards which a continuous blend keeps the time constants continuous, and the
                regressors' η̂ do not depend on the classifier being sure. One rule cannot give both
                bit for bit: a hard switch is not the ramp λ (and compares max p with c₀ Σ p, not
                c with c₀), and their fallback targets differ.
3. noise removal  a_d = a − w_a η̂_a,  m_d = m − w_m η̂_m  (``remove_noise``; w in [0, 1])
4. back-off     a heading/magnetometer gain k becomes k / (1 + e), e = |η̂_m|² / σ_m²
                (``predicted_disturbance``, ``back_off``; σ_m [µT] > 0)

The kernels of steps 1-4 are numba functions that take the ``PredictionLayout`` (a ``NamedTuple`` of
ints, a field of the filters' coefficients) and the row ``(S + 6,)``.
"""
from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
from numba import njit

from togglecf.filters.base import FilterOutput, OrientationFilter

__all__ = [
    "LEARNED",
    "LOW_CONFIDENCE",
    "NO_PREDICTION",
    "N_PRED_NOISE",
    "PredictionDrivenFilter",
    "PredictionLayout",
    "back_off",
    "blend_trust",
    "class_evidence",
    "noise_finite",
    "params_by_value",
    "predicted_disturbance",
    "remove_noise",
    "run_batch_predicted",
    "switch_status",
]

#: the predicted noise after the probabilities: η̂_a (3) then η̂_m (3)
N_PRED_NOISE = 6
#: ``switch_status``: the models' prediction is used, or the fallback for want of a valid prediction or of confidence
LEARNED, NO_PREDICTION, LOW_CONFIDENCE = 0, 1, 2
_AXES = ("x", "y", "z")


class PredictionLayout(NamedTuple):
    """Where the parts of a prediction row ``[p_1..p_S, η̂_a (3), η̂_m (3)]`` are: indices into the
    row (numba reads the fields) and, for arrays of rows ``(..., size)`` in Python, the slices
    ``probabilities``, ``eta_acc``, ``eta_mag`` and ``eta``. Build it with ``PredictionLayout.of(S)``."""

    n_states: int  # S: the class probabilities are row[0:S]
    eta_acc_index: int  # row index of η̂_a,x [m/s²]; η̂_a,y and η̂_a,z follow
    eta_mag_index: int  # row index of η̂_m,x [µT]; η̂_m,y and η̂_m,z follow
    size: int  # the row length, S + 6

    @classmethod
    def of(cls, n_states: int) -> "PredictionLayout":
        """The layout of a row for ``n_states`` motion states."""
        n = int(n_states)
        return cls(n, n, n + 3, n + N_PRED_NOISE)

    @property
    def probabilities(self) -> slice:
        return slice(0, self.n_states)

    @property
    def eta_acc(self) -> slice:
        return slice(self.eta_acc_index, self.eta_acc_index + 3)

    @property
    def eta_mag(self) -> slice:
        return slice(self.eta_mag_index, self.eta_mag_index + 3)

    @property
    def eta(self) -> slice:
        """Both predicted noise vectors, η̂_a then η̂_m."""
        return slice(self.eta_acc_index, self.size)

    def names(self, class_names) -> list[str]:
        """The entries' names: ``p_<state>`` per class, then ``eta_acc_x`` ... ``eta_mag_z``."""
        if len(class_names) != self.n_states:
            raise ValueError(f"{len(class_names)} class names for a layout of {self.n_states} states")
        return [f"p_{s}" for s in class_names] + [f"eta_{t}_{ax}" for t in ("acc", "mag") for ax in _AXES]

    def outputs(self, part: slice) -> list[int]:
        """The row indices of ``part`` (e.g. ``layout.eta_mag``)."""
        return list(range(self.size))[part]


@njit(cache=True, inline="always")
def class_evidence(layout, row):
    """Step 1: ``(valid, top, total)``: whether the probabilities are valid (every p_s finite and
    ≥ 0, and Σ p_s > 0), their largest max_s p_s and their sum Σ_s p_s (in class order)."""
    total = 0.0
    top = 0.0
    valid = True
    for s in range(layout.n_states):
        v = row[s]
        if not (v >= 0.0 and v < math.inf):
            valid = False
        else:
            total += v
            top = max(top, v)
    return valid and total > 0.0, top, total


@njit(cache=True, inline="always")
def switch_status(valid, top, total, floor):
    """Step 2, the toggling CF's rule (module docstring): ``LEARNED``, ``NO_PREDICTION`` (not
    valid) or ``LOW_CONFIDENCE`` (max p < c₀ Σ p, with ``floor`` c₀ in [0, 1))."""
    if not valid:
        return NO_PREDICTION
    if top < floor * total:
        return LOW_CONFIDENCE
    return LEARNED


@njit(cache=True, inline="always")
def blend_trust(valid, top, total, floor):
    """Step 2, the learned VQF's rule (module docstring): the trust λ in [0, 1] of the learned
    values, clip((c − c₀)/(1 − c₀), 0, 1) with c = top/total and ``floor`` c₀ in [0, 1); 0 when not valid."""
    if not valid:
        return 0.0
    return min(max((top / total - floor) / (1.0 - floor), 0.0), 1.0)


@njit(cache=True, inline="always")
def noise_finite(layout, row):
    """True when η̂_a and η̂_m are all finite."""
    ok = True
    for j in range(N_PRED_NOISE):
        if not math.isfinite(row[layout.eta_acc_index + j]):
            ok = False
    return ok


@njit(cache=True, inline="always")
def remove_noise(layout, row, acc, mag, w_a, w_m, use):
    """Step 3: ``(removed, a_d, m_d)``: (True, a − w_a η̂_a, m − w_m η̂_m) when ``use`` and η̂ is
    finite, else (False, a, m) (3-tuples; a [m/s²], m [µT], weights dimensionless). ``removed``
    also says whether η̂ may drive the back-off (step 4) under the same rule."""
    if use and noise_finite(layout, row):
        i, j = layout.eta_acc_index, layout.eta_mag_index
        a_d = (acc[0] - w_a * row[i], acc[1] - w_a * row[i + 1], acc[2] - w_a * row[i + 2])
        m_d = (mag[0] - w_m * row[j], mag[1] - w_m * row[j + 1], mag[2] - w_m * row[j + 2])
        return True, a_d, m_d
    return False, (acc[0], acc[1], acc[2]), (mag[0], mag[1], mag[2])


@njit(cache=True, inline="always")
def predicted_disturbance(layout, row, sigma):
    """Step 4: e = |η̂_m|² / σ_m² (dimensionless) for ``sigma`` σ_m [µT] > 0; 0 for a NaN η̂_m."""
    j = layout.eta_mag_index
    e0, e1, e2 = row[j], row[j + 1], row[j + 2]
    e = (e0 * e0 + e1 * e1 + e2 * e2) / (sigma * sigma)
    return e if e >= 0.0 else 0.0  # False for NaN


@njit(cache=True, inline="always")
def back_off(gain, e):
    """Step 4: a magnetometer gain lowered by the disturbance e ≥ 0: k / (1 + e)."""
    return gain / (1.0 + e)


# ------------------------------------------------------------------------------------------
# The filters driven by one prediction row per sample
# ------------------------------------------------------------------------------------------

@njit(cache=False)
def run_batch_predicted(step, state, params, gyr, acc, mag, dt, pred, quat_out, diag_out):
    """``run_batch`` with one prediction row per sample."""
    for i in range(gyr.shape[0]):
        step(state, params, gyr[i], acc[i], mag[i], dt[i], pred[i], diag_out[i])
        quat_out[i, 0] = state[0]
        quat_out[i, 1] = state[1]
        quat_out[i, 2] = state[2]
        quat_out[i, 3] = state[3]


def params_by_value(params):
    """``params`` (a coefficients record) with its non-empty 1-D float64 arrays as tuples of the same
    values (``PredictionDrivenFilter.step_params``; the steps only index these fields)."""
    conv = {k: tuple(float(x) for x in v) for k, v in params._asdict().items()
            if isinstance(v, np.ndarray) and v.ndim == 1 and v.size and v.dtype == np.float64}
    return params._replace(**conv) if conv else params


class PredictionDrivenFilter(OrientationFilter):
    """A filter whose step also takes one prediction row per sample: ``step(state, params, gyr,
    acc, mag, dt, pred, diag)`` with ``pred`` = ``[p_1..p_S, η̂_a (3), η̂_m (3)]`` (class
    probabilities of ``settings.states``, then the predicted acc/mag noise in the sensor frame,
    m/s² and µT; ``filters.prediction``). ``update``/``update_batch`` take the predictions beside
    the IMU samples; with none given, ``_default_pred`` stands in ("no model")."""

    #: the ``params`` whose by-value copy ``step_params`` holds (None: none made yet)
    _step_params_of = None

    @classmethod
    def settings_for(cls, class_names, rest_state: str, **overrides):
        """Settings for a model whose classes are ``class_names`` (its rest class ``rest_state``), as
        ``states``, built in one go so that per-state defaults match their number; ``overrides``
        replace fields (``states`` too)."""
        return cls.Settings(**{"states": tuple(class_names), **overrides})

    def step_params(self):
        """``self.params`` as the step gets it: its non-empty 1-D float arrays as tuples of the same
        values (``params_by_value``), rebuilt when ``self.params`` is replaced. Why: numba
        reference-counts every array of a record at each call of the step, while a tuple of floats is
        passed as plain values; and every loop that runs the step (``update_batch``, the in-loop
        models' ``toggling.inloop``) passes the same types, so it is compiled once."""
        if self._step_params_of is not self.params:
            self._step_params_of, self._step_params_value = self.params, params_by_value(self.params)
        return self._step_params_value

    @property
    def layout(self) -> PredictionLayout:
        """The layout of this filter's prediction rows (``filters.prediction``)."""
        return PredictionLayout.of(len(self.settings.states))

    @property
    def uses_class_probabilities(self) -> bool:
        """Whether the class probabilities can change this filter's output (default True); the in-loop
        models do not walk the classifier's trees of a filter that says no (``toggling.inloop``)."""
        return True

    @property
    def n_predictions(self) -> int:
        return self.layout.size

    def _default_pred(self, n):
        raise NotImplementedError

    def update(self, gyr, acc, mag=None, dt=None, prediction=None) -> np.ndarray:
        pred = self._default_pred(1)[0] if prediction is None else np.asarray(prediction, np.float64)
        if pred.shape != (self.n_predictions,):
            raise ValueError(f"prediction: expected shape ({self.n_predictions},), got {pred.shape}")
        g, a, m, dt_arr = self.batch_inputs(np.reshape(gyr, (1, 3)), np.reshape(acc, (1, 3)),
                                       None if mag is None else np.reshape(mag, (1, 3)), dt)
        type(self).step(self.state, self.step_params(), g[0], a[0], m[0], dt_arr[0], pred, self._diag)
        return self.quat

    def update_batch(self, gyr, acc, mag=None, dt=None, predictions=None):
        g, a, m, dt_arr = self.batch_inputs(gyr, acc, mag, dt)
        n = g.shape[0]
        pred = self._default_pred(n) if predictions is None else np.ascontiguousarray(predictions, np.float64)
        if pred.shape != (n, self.n_predictions):
            raise ValueError(f"predictions: expected shape ({n}, {self.n_predictions}), got {pred.shape}")
        quat_out = np.empty((n, 4))
        diag_out = np.zeros((n, len(self.diagnostic_names)))
        run_batch_predicted(type(self).step, self.state, self.step_params(), g, a, m, dt_arr, pred, quat_out, diag_out)
        if n:
            self._diag[:] = diag_out[-1]
        return FilterOutput(quat_out, {k: diag_out[:, i] for i, k in enumerate(self.diagnostic_names)})
