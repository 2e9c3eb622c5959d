"""Learning the toggling filter's gains on training trials (coordinate descent on BROAD RMSE).

The models' predictions do not depend on the gains, so they are computed once per trial
(``CompiledModels.predict_samples``) and every candidate setting only re-runs the cheap
filter core. Each parameter is searched on its own grid while the others are held; a few
sweeps over all parameters converge on these smooth objectives.

The objective (``OBJECTIVES``) is built on BROAD's total RMSE per trial (6D: with the constant
heading offset removed):

* ``"worst_dataset_log_ratio"`` (default): per trial ln(RMSE / RMSE at the start), the start being
  learning off; averaged per dataset (the ``<dataset>/`` prefix of a trial's name; one dataset
  when there is none); the worst dataset's mean, plus 10⁻³ × the mean over datasets to break
  ties. No dataset can dominate: a change is kept only where it helps the dataset it helps least,
  and a trial counts by its relative change, so the datasets with the largest errors do not choose
  the values for everyone.
* ``"mean_dataset_log_ratio"``: the same per-dataset means, averaged over the datasets, and no step may leave a
  dataset's mean above 0 (worse than learning off: the value is then +inf). A change that helps some datasets
  beyond the scatter and the others less, or not at all, can be kept, where the worst dataset's mean refuses it
  (it must help every dataset beyond the scatter); no training dataset pays for another's gain. With one dataset
  it is that dataset's mean.
* ``"mean_rmse"``: the mean total RMSE over all trials (the trials with the largest errors weigh most).

When a step is kept (``STEP_RULES``): ``"any_gain"`` keeps a candidate that lowers the objective at
all; ``"one_se"`` (the default of both searches: the learned VQF's, whose start is the VQF core, and
the toggling CF's, whose start is ``GainSearch.start``) keeps it only when it lowers the objective by
more than one standard error of its per-trial change (Breiman's one-standard-error rule,
``step_margin``): a learned value leaves the start only for a gain the training trials show beyond
their own trial-to-trial scatter, not for a few tenths of a percent that need not travel.
"""
from __future__ import annotations

import hashlib
import json
import logging
import math
import multiprocessing as mp
import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import NamedTuple

import numpy as np
from numba import njit

from togglecf.core.io import atomic_write_json, check_keys
from togglecf.core.progress import progress
from togglecf.filters.toggling import TogglingFilter, TogglingSettings
from togglecf.filters.vqf_toggling import VQFTogglingFilter, VQFTogglingSettings
from togglecf.learn.compiled import CompiledModels
from togglecf.learn.models import load_bundle
from togglecf.metrics.broad import error_angles_rad, error_quaternion, remove_heading_offset, rmse_deg

__all__ = ["GainSearch", "VQFGainSearch", "MODES", "OBJECTIVES", "STEP_RULES", "objective_value", "step_margin", "trial_datasets", "filter_for", "learn_gains", "mean_total_rmse", "trials_digest", "EvaluationMemo", "EVALUATIONS", "save_gains", "load_gains", "learn_and_save_gains", "learn_modes", "LearnedGains", "GAINS_FILE", "GAINS_FORMAT", "check_gains_format", "settings_from_dict", "mode_name"]

logger = logging.getLogger(__name__)

#: s: the per-sample grid (0, 0.00003, 0.0001, 0.0002, 0.0005, 0.001, 0.002, 0.005, 0.01, 0.02,
#: 0.05) at BROAD's 285.714 Hz as time constants (``timeconst.tau_from_gain``, 4 digits; −1 = off)
_TAU_GRID = (-1.0, 116.7, 35.0, 17.5, 6.998, 3.498, 1.748, 0.6982, 0.3482, 0.1732, 0.06824)

#: ``gains.json`` format: 2 = time constants [s] and the training rate(s) (``trained_fs``);
#: 1 (no ``format`` key) = per-sample gains at the training rate, refused by ``load_gains``
GAINS_FORMAT = 2

#: objectives of the descent (module docstring)
OBJECTIVES = ("worst_dataset_log_ratio", "mean_dataset_log_ratio", "mean_rmse")
#: weight of the mean over datasets beside the worst one (ties of the worst dataset)
_TIE_BREAK = 1e-3
#: when the descent keeps a step (module docstring)
STEP_RULES = ("any_gain", "one_se")
#: the least decrease of the objective a kept step needs (a float tie is no step)
_MIN_STEP = 1e-9


def trial_datasets(trials) -> np.ndarray:
    """The dataset of each trial (a ``Trial`` or its name): the ``<dataset>/`` prefix of its name
    (``MultiIndex``), else ``""``."""
    parts = (str(getattr(t, "name", t)).partition("/") for t in trials)
    return np.array([head if sep else "" for head, sep, _ in parts])


def objective_value(name: str, rmse, start_rmse, datasets) -> float:
    """The descent's objective ``name`` (``OBJECTIVES``) from per-trial total RMSEs [deg] ``rmse``,
    the same at the descent's start ``start_rmse`` and each trial's dataset (``trial_datasets``).
    Trials whose RMSE is not finite (no scored sample) are left out."""
    rmse, start_rmse = np.asarray(rmse, np.float64), np.asarray(start_rmse, np.float64)
    if name == "mean_rmse":
        return float(np.mean(rmse))
    if name not in OBJECTIVES:
        raise ValueError(f"gain objective must be one of {OBJECTIVES}, got {name!r}")
    datasets = np.asarray(datasets)
    ok, ratio = _log_ratios(rmse, start_rmse)
    per = [float(np.mean(ratio[ok & (datasets == d)])) for d in np.unique(datasets[ok])]
    if not per:
        return float("nan")
    if name == "mean_dataset_log_ratio":
        return float(np.mean(per)) if max(per) <= 0.0 else math.inf
    return max(per) + _TIE_BREAK * float(np.mean(per))


def _log_ratios(rmse, reference):
    """``(ok, ln(rmse / reference))`` per trial; ``ok`` where both are finite and ``reference > 0``
    (elsewhere the ratio is 0 and must be left out)."""
    ok = np.isfinite(rmse) & np.isfinite(reference) & (reference > 0)
    return ok, np.log(np.where(ok, rmse, 1.0) / np.where(ok, reference, 1.0))


def step_margin(rule: str, objective: str, rmse, current_rmse, datasets) -> float:
    """How much a candidate with per-trial total RMSEs ``rmse`` [deg] must lower the objective
    ``objective`` below the current settings' (``current_rmse``) to be kept, under ``rule``
    (``STEP_RULES``): 0 for ``"any_gain"``; for ``"one_se"`` the standard error of the mean per-trial
    change: of ln(rmse / current) per dataset, the largest taken, for the worst dataset's objective; of the
    mean over datasets of those means, √(Σ SE²) / D, for ``"mean_dataset_log_ratio"``; of the RMSE
    difference [deg] over all trials for ``"mean_rmse"`` (a group of one trial has none)."""
    if rule == "any_gain":
        return 0.0
    if rule != "one_se":
        raise ValueError(f"gain-search step rule must be one of {STEP_RULES}, got {rule!r}")
    rmse, current_rmse = np.asarray(rmse, np.float64), np.asarray(current_rmse, np.float64)
    ok, change = _log_ratios(rmse, current_rmse)
    ok &= rmse > 0
    groups = np.asarray(datasets)
    if objective == "mean_rmse":
        change, groups = rmse - current_rmse, np.zeros(len(rmse), dtype=int)
    se = [float(np.std(change[ok & (groups == g)], ddof=1) / math.sqrt(n))
          for g in np.unique(groups[ok]) if (n := int(np.sum(ok & (groups == g)))) > 1]
    if objective == "mean_dataset_log_ratio":  # the SE of a mean of independent per-dataset means
        return math.sqrt(sum(v * v for v in se)) / len(np.unique(groups[ok])) if se else 0.0
    return max(se, default=0.0)


def _check_search(search, what: str) -> None:
    if search.objective not in OBJECTIVES:
        raise ValueError(f"{what} objective must be one of {OBJECTIVES}, got {search.objective!r}")
    if search.step_rule not in STEP_RULES:
        raise ValueError(f"{what} step_rule must be one of {STEP_RULES}, got {search.step_rule!r}")


def _search_from_dict(cls, d: dict, what: str):
    """A gain-search record from a config table: lists become tuples of floats (the grids), other
    values (``sweeps``) stay; unknown keys are refused (``check_keys``)."""
    return cls(**{k: tuple(float(x) for x in v) if isinstance(v, (list, tuple)) else v
                  for k, v in check_keys(cls, d, what).items()})


@dataclass(frozen=True)
class GainSearch:
    """Grids of the coordinate descent (time constants in s, ``TogglingSettings``; σ_m in µT). The
    defaults are round per-sample gains at BROAD's 285.714 Hz, written as time constants.

    Attributes:
        tau: grid of every per-state acc and mag time constant [s] (< 0: that correction off).
        output_tau: grid of the output blend's time constant [s] (0: vectors only).
        bias_tau: grid of the rest-bias low-pass time constant [s] (< 0: no bias estimate).
        bias_gate: grid of the largest |ω − b| [rad/s] taken as bias.
        mag_disturbance_scale: grid of σ_m [µT] (0 = off); none below 10 µT by default, as the learned
            VQF's: a smaller σ_m backs off on a consumer magnetometer's calibration residuals (a
            few µT), a quirk of the sensor rather than a disturbance. The back-off itself is bounded
            by ``TogglingSettings.mag_rejection_factor`` (not searched).
        noise_weight_acc, noise_weight_mag: grids of the weights of the predicted noise (default 0
            only: a noise vector learned on one sensor does not belong in another's signal).
        confidence_floor: grid of the confidence floor c₀ (0: never fall back on a valid prediction).
        mag_rate_limit: grid of the heading correction's rate bound ω_m [rad/s] (0: none; 9D), the
            first coordinate of the descent: the per-state τ_mag are then searched with the bound
            in place (a bound makes a fast τ_mag safe in a disturbed field). None between 0 and 0.02 rad/s
            (about 1 °/s, a consumer gyroscope's bias): the bias is learned fully only at predicted rest (in
            motion only about the vertical, and only where the field passes step 5b's check), and a bound
            below the bias left in motion cannot hold the heading against it.
        sweeps: passes over all parameters.
        objective: what the descent minimises (``OBJECTIVES``, module docstring).
        step_rule: when a step is kept (``STEP_RULES``, module docstring): by default one standard
            error (``"one_se"``), as the learned VQF's search: a value learned on the training
            datasets leaves the start only for a gain beyond their trial-to-trial scatter.
    """

    tau: tuple = _TAU_GRID
    output_tau: tuple = (0.009813, 0.00382, 0.0)  # γ 0.3, 0.6, 1 at 285.714 Hz
    bias_tau: tuple = (-1.0, 11.66, 3.498, 1.165)  # gains 0, 0.0003, 0.001, 0.003 at 285.714 Hz
    bias_gate: tuple = (0.02, 0.05)
    mag_disturbance_scale: tuple = (0.0, 10.0, 30.0)
    noise_weight_acc: tuple = (0.0,)
    noise_weight_mag: tuple = (0.0,)
    confidence_floor: tuple = (0.0,)
    mag_rate_limit: tuple = (0.0, 0.02, 0.05)
    sweeps: int = 2
    objective: str = "worst_dataset_log_ratio"
    step_rule: str = "one_se"

    def __post_init__(self):
        _check_search(self, "gain-search")

    @classmethod
    def from_dict(cls, d: dict) -> "GainSearch":
        return _search_from_dict(cls, d, "gain-search")

    def start(self, states, static_state) -> TogglingSettings:
        """Where the descent starts: moderate gains in every state (τ_acc 3.498 s, τ_mag 11.66 s,
        bias 3.498 s: the per-sample gains 0.001, 0.0003, 0.001 at 285.714 Hz) and the noise
        regressors off (w_a = w_m = 0, σ_m = 0, no confidence floor), as the VQF search starts at
        learning off: a learned term is used only where it lowered the objective on the training
        trials (a noise removal learned on BROAD did not travel to the phone data)."""
        n = len(states)
        return TogglingSettings(states=tuple(states), static_state=static_state, tau_acc=(3.498,) * n,
                                tau_mag=(11.66,) * n, output_tau=0.0, bias_tau=3.498, noise_weight_acc=0.0,
                                noise_weight_mag=0.0, mag_disturbance_scale=0.0, confidence_floor=0.0)

    def candidates(self, settings: TogglingSettings, use_mag: bool = True):
        """(label, [(value, change), ...]) for each coordinate of the descent."""
        n = len(settings.states)
        if use_mag:
            yield "mag_rate_limit", [(v, {"mag_rate_limit": v}) for v in self.mag_rate_limit]
        for name in ("tau_acc", "tau_mag") if use_mag else ("tau_acc",):
            for s in range(n):
                vals = []
                for a in self.tau:
                    g = list(getattr(settings, name))
                    g[s] = a
                    vals.append((a, {name: tuple(g)}))
                yield f"{name}[{settings.states[s]}]", vals
        for name in ("noise_weight_acc", "noise_weight_mag", "output_tau", "bias_tau", "bias_gate") + (
                ("mag_disturbance_scale",) if use_mag else ()) + ("confidence_floor",):
            yield name, [(v, {name: v}) for v in getattr(self, name)]


@dataclass(frozen=True)
class VQFGainSearch:
    """Grids of the coordinate descent of the VQF core's learned time constants
    (``filters.vqf_toggling``): per state τ_acc [s], τ_mag [s] (9D), σ_motion [°/s] and the rest
    thresholds th_ω [°/s], th_a [m/s²]; the confidence floor c₀; the predicted-disturbance scale
    σ_m [µT] of the heading gain (9D); the noise weights. The descent starts at the core's own
    settings (learning off), so on the training trials it can only improve on the core.

    By default only what travels between sensors is learned: τ_acc per state and the
    heading back-off σ_m of a predicted disturbance (µT, of the predicted noise); τ_mag, the rest
    thresholds (m/s², °/s: properties of the sensor's noise) and the noise-vector weights
    (subtracting a noise vector learned on one sensor from another's signal) keep the core's
    values (grids of one value); the measurement is in docs/concepts/vqf-core.md.

    σ_motion's grid is the core's value alone (not learned) by default: it is the steady-state
    uncertainty of the gyro-bias estimate, a property of the gyroscope rather than of the motion,
    and values learned per state on one sensor do not travel to another (the measurement is in
    docs/concepts/vqf-core.md). A grid of several values still learns it, for data of one
    sensor.

    σ_m's grid starts at 10 µT (a fifth of the Earth's field): a smaller σ_m backs off on the
    calibration residuals of a consumer magnetometer (a few µT): a sensor quirk, not a
    disturbance. This floor was set after seeing a leave-one-dataset-out result (σ_m = 3 µT, learned
    on BROAD and the iPhone 4S, made the Nexus 5's swinging trials worse than the core). Whatever
    σ_m, the back-off is bounded by the core's rejection factor (``VQFTogglingSettings``).

    σ_f, the scale of the back-off on the field's change in the 6D earth frame (step 3b of
    ``filters.vqf_toggling``: no model, a physical cue), is off (0) by default; a grid of several
    values searches it (9D), for data of one sensor (``togglecf train --from-pretrained`` does by default:
    ``run.config.relearn_search``).

    A step is kept by the one-standard-error rule (``step_rule = "one_se"``, module docstring): the
    descent starts at the core, and a value leaves it only for a gain larger than the scatter of
    that gain over the training trials."""

    tau_acc: tuple = (0.5, 1.0, 2.0, 3.0, 5.0, 8.0, 15.0, 30.0)
    tau_mag: tuple = (9.0,)
    bias_sigma_motion: tuple = (0.1,)
    rest_th_gyr: tuple = (2.0,)
    rest_th_acc: tuple = (0.5,)
    confidence_floor: tuple = (0.0, 0.5, 0.7)
    mag_disturbance_scale: tuple = (0.0, 10.0, 30.0)
    field_change_scale: tuple = (0.0,)
    noise_weight_acc: tuple = (0.0,)
    noise_weight_mag: tuple = (0.0,)
    sweeps: int = 2
    objective: str = "worst_dataset_log_ratio"
    step_rule: str = "one_se"
    modulation_tau: float = 3.0

    def __post_init__(self):
        _check_search(self, "VQF gain-search")

    @classmethod
    def from_dict(cls, d: dict) -> "VQFGainSearch":
        return _search_from_dict(cls, d, "VQF gain-search")

    def start(self, states, static_state=None) -> VQFTogglingSettings:
        """The core's own settings (learning off) with ``modulation_tau`` [s], the time constant with
        which the learned τ_acc, τ_mag follow the predictions (``VQFTogglingSettings``; not searched:
        a time constant changes no faster than the time scale it sets, VQF's τ_acc of 3 s)."""
        return VQFTogglingSettings(states=tuple(states), modulation_tau=float(self.modulation_tau))

    def candidates(self, settings: VQFTogglingSettings, use_mag: bool = True):
        n = len(settings.states)
        grids = (("tau_acc_states", self.tau_acc), ("bias_sigma_motion_states", self.bias_sigma_motion),
                 ("rest_th_gyr_states", self.rest_th_gyr), ("rest_th_acc_states", self.rest_th_acc)) + (
            (("tau_mag_states", self.tau_mag),) if use_mag else ())
        for name, grid in grids:
            for s in range(n):
                vals = []
                for v in grid:
                    g = list(getattr(settings, name))
                    g[s] = v
                    vals.append((v, {name: tuple(g)}))
                yield f"{name}[{settings.states[s]}]", vals
        for name in ("confidence_floor", "noise_weight_acc") + (
                ("noise_weight_mag", "mag_disturbance_scale", "field_change_scale") if use_mag else ()):
            yield name, [(v, {name: v}) for v in getattr(self, name)]


#: gain modes of ``togglecf train`` ([gains] modes): mode -> (filter, 9D)
MODES = {"9d": ("toggling", True), "6d": ("toggling", False), "vqf_9d": ("vqf_toggling", True),
         "vqf_6d": ("vqf_toggling", False)}
_SETTINGS_OF = {"toggling": TogglingSettings, "vqf_toggling": VQFTogglingSettings}
_FILTER_OF = {TogglingSettings: TogglingFilter, VQFTogglingSettings: VQFTogglingFilter}
_KIND_OF = {v: k for k, v in _SETTINGS_OF.items()}


def filter_for(settings):
    """The prediction-driven filter class that runs ``settings``."""
    return _FILTER_OF[type(settings)]


def _trial_total(t, pred, settings, use_mag) -> float:
    f = filter_for(settings)(t.fs, settings, use_mag=use_mag)
    q = f.update_batch(t.gyr, t.acc, t.mag if use_mag else None, predictions=pred).quat
    if not use_mag:
        q = remove_heading_offset(q, t.opt_quat, t.movement)
        return rmse_deg(error_angles_rad(error_quaternion(q, t.opt_quat))["total"], t.movement)
    return _total_rmse_deg(q, t.opt_quat, t.movement)


@njit(cache=True)
def _total_rmse_deg(q_est, q_ref, movement):
    """BROAD's total RMSE [deg] fused in one loop (the objective is evaluated thousands of times);
    equal to ``evaluation.trial_errors(...)["total"]`` (test)."""
    s = 0.0
    k = 0
    for i in range(q_est.shape[0]):
        if not movement[i]:
            continue
        a, b = q_est[i], q_ref[i]
        if not (math.isfinite(b[0]) and math.isfinite(a[0])):
            continue
        na = math.sqrt(a[0] * a[0] + a[1] * a[1] + a[2] * a[2] + a[3] * a[3])
        nb = math.sqrt(b[0] * b[0] + b[1] * b[1] + b[2] * b[2] + b[3] * b[3])
        w = abs(a[0] * b[0] + a[1] * b[1] + a[2] * b[2] + a[3] * b[3]) / (na * nb)  # |w| of q_est ⊗ q_ref*
        e = 2.0 * math.acos(min(1.0, w))
        s += e * e
        k += 1
    return math.degrees(math.sqrt(s / k)) if k else math.nan


def trial_total_rmse(settings, trials, predictions, use_mag: bool = True, pool=None) -> np.ndarray:
    """BROAD's total RMSE [deg] per trial of the learned filter with ``settings`` ``(n_trials,)``.
    ``pool``: an ``_TrialPool`` (from ``learn_gains``) to spread the trials over processes."""
    if pool is not None:
        return np.array(pool.map(settings, use_mag), np.float64)
    return np.array([_trial_total(t, p, settings, use_mag) for t, p in zip(trials, predictions)], np.float64)


def trials_digest(trials, predictions) -> str:
    """sha256 of what a gain evaluation reads: each trial's name, rate, IMU signals, reference and
    ``movement``, and its predictions (the key of ``EvaluationMemo``)."""
    h = hashlib.sha256()
    for t, p in zip(trials, predictions):
        h.update(f"{t.name}|{float(t.fs)!r}|".encode())
        for a in (t.gyr, t.acc, t.mag, t.opt_quat, t.movement, p):
            a = np.ascontiguousarray(a)
            h.update(f"{a.dtype.str}{a.shape}".encode())
            h.update(a.tobytes())
    return h.hexdigest()


class EvaluationMemo:
    """Per-trial total RMSEs already computed in this process, keyed on content (``trials_digest``
    of the trials and predictions, the settings' ``repr`` with every float exact, 6D/9D): a gain
    search that meets a setting again (the last sweep of a coordinate descent re-tries what the
    sweep before tried at the same point; the study's ablations repeat the main search where their
    grids coincide) takes the stored values, which are the same floats as a recomputation.
    Bounded: the oldest entries go first beyond ``max_entries``."""

    def __init__(self, max_entries: int = 100_000):
        self.max_entries = int(max_entries)
        self.values: dict = {}
        self.hits = 0

    def get(self, key):
        v = self.values.get(key)
        if v is not None:
            self.hits += 1
        return v

    def put(self, key, value: np.ndarray) -> None:
        while len(self.values) >= self.max_entries:
            self.values.pop(next(iter(self.values)))
        self.values[key] = np.array(value, np.float64)


#: the process's memo of gain evaluations (``learn_gains``)
EVALUATIONS = EvaluationMemo()


def mean_total_rmse(settings: TogglingSettings, trials, predictions, use_mag: bool = True, pool=None) -> float:
    """Mean over trials of BROAD's total RMSE [deg] of the toggling filter with ``settings``."""
    return float(np.mean(trial_total_rmse(settings, trials, predictions, use_mag, pool)))


_WORK = {}


def _pool_task(i, settings, use_mag):  # noqa: D103 (runs in a forked worker)
    t, p = _WORK["trials"][i], _WORK["predictions"][i]
    return _trial_total(t, p, settings, use_mag)


class _TrialPool:
    """Fork workers that inherit the trials and predictions (nothing large is pickled)."""

    def __init__(self, trials, predictions, jobs, filter_cls=TogglingFilter):
        _WORK["trials"], _WORK["predictions"] = list(trials), list(predictions)
        filter_cls(100.0).update_batch(np.zeros((2, 3)), np.ones((2, 3)), np.ones((2, 3)))  # compile before forking
        self.n = len(trials)
        self.ex = ProcessPoolExecutor(jobs, mp_context=mp.get_context("fork"))

    def map(self, settings, use_mag):
        return list(self.ex.map(_pool_task, range(self.n), [settings] * self.n, [use_mag] * self.n))

    def close(self):
        self.ex.shutdown()
        _WORK.clear()


def learn_gains(trials, predictions, states, static_state, use_mag: bool = True, search: GainSearch | None = None,
                start: TogglingSettings | None = None, verbose: bool = False, jobs: int = 1,
                memo: EvaluationMemo | None = EVALUATIONS):
    """Coordinate descent from ``start`` (default: moderate gains). Returns ``(settings, history)``
    with ``history`` a list of ``(parameter, value, objective)`` after each accepted step.
    ``jobs > 1`` spreads the trials over that many forked processes. ``memo``: evaluations already
    made (default: this process's ``EVALUATIONS``; ``None``: compute every one)."""

    # a daemonic process (a Dask worker, a pool worker) may not fork a pool: evaluate in-process there
    parallel = jobs > 1 and len(trials) > 1 and not mp.current_process().daemon
    search = search or GainSearch()
    probe = start or search.start(states, static_state)
    pool = _TrialPool(trials, predictions, jobs, filter_for(probe)) if parallel else None
    try:
        return _descend(trials, predictions, states, static_state, use_mag, search, start, verbose, pool, memo)
    finally:
        if pool is not None:
            pool.close()


def _descend(trials, predictions, states, static_state, use_mag, search, start, verbose, pool, memo):
    settings = start or search.start(states, static_state)
    datasets = trial_datasets(trials)
    digest = trials_digest(trials, predictions) if memo is not None else None

    def rmse_of(s):  # computed once per content and setting (``memo``)
        if memo is None:
            return trial_total_rmse(s, trials, predictions, use_mag, pool)
        key = (digest, repr(s), bool(use_mag))
        got = memo.get(key)
        if got is None:
            got = trial_total_rmse(s, trials, predictions, use_mag, pool)
            memo.put(key, got)
        return got

    at_start = rmse_of(settings)

    def objective(rmse):
        return objective_value(search.objective, rmse, at_start, datasets)

    best, current = objective(at_start), at_start
    history = [("start", None, best)]
    coords = list(search.candidates(settings, use_mag))
    for sweep in range(search.sweeps):
        improved = False
        for label, _ in progress(coords, desc=f"gains sweep {sweep + 1}", unit="param"):
            cands = dict(search.candidates(settings, use_mag))[label]  # rebuilt from the current settings
            for value, change in cands:
                trial_settings = replace(settings, **change)
                if trial_settings == settings:
                    continue
                rmse = rmse_of(trial_settings)
                obj = objective(rmse)
                margin = step_margin(search.step_rule, search.objective, rmse, current, datasets)
                if obj < best - max(_MIN_STEP, margin):
                    best, settings, current, improved = obj, trial_settings, rmse, True
                    history.append((label, value, obj))
            if verbose:
                logger.info(f"  {label}: {search.objective} {best:.4f}")
        if not improved:
            break
    return settings, history


GAINS_FILE = "gains.json"


_OBJECTIVE_TEXT = {
    "mean_rmse": "mean total RMSE [deg] over the trials (BROAD)",
    "worst_dataset_log_ratio": "worst dataset's mean ln(total RMSE / at learning off) per trial, + 1e-3 x the mean "
                               "over datasets (BROAD's total RMSE)",
    "mean_dataset_log_ratio": "mean over datasets of each dataset's mean ln(total RMSE / at learning off) per "
                              "trial, no dataset above learning off (BROAD's total RMSE)"}


def save_gains(model_dir, settings: TogglingSettings, trials, history, use_mag: bool = True,
               predictions: str = "in-sample", search=None):
    """Write ``gains.json`` beside the models (atomically): ``"format": GAINS_FORMAT``, the learned
    settings (time constants in s), the trials they were learned on and their sampling rate(s)
    (``trained_fs`` [Hz], per mode and for the file), the objective history and the models'
    schema hash they belong to. ``search``: the ``GainSearch``/``VQFGainSearch`` that learned them
    (its objective is named; ``None``: settings fixed by hand). A file of the old format is replaced,
    not merged into."""
    model_dir = Path(model_dir)
    meta = json.loads((model_dir / "metadata.json").read_text())
    key = mode_name(_KIND_OF[type(settings)], use_mag)
    path = model_dir / GAINS_FILE
    doc = json.loads(path.read_text()) if path.is_file() else {}
    if doc.get("format") != GAINS_FORMAT:
        doc = {}
    rates = sorted({round(float(t.fs), 6) for t in trials if getattr(t, "fs", None) is not None})
    doc["format"] = GAINS_FORMAT
    doc["units"] = "time constants in s (per-sample gain k = 1 - exp(-Ts/tau) at the filter's rate)"
    doc["feature_schema_hash"] = meta["feature_schema"]["hash"]
    doc["trained_fs"] = sorted(set(doc.get("trained_fs", [])) | set(rates))
    doc[key] = {"filter": _KIND_OF[type(settings)], "settings": asdict(settings), "trained_fs": rates,
                "trials": [getattr(t, "name", t) for t in trials],
                "objective": _OBJECTIVE_TEXT[search.objective] if search is not None else "none (not learned)",
                "step_rule": search.step_rule if search is not None else None,
                "predictions": predictions,
                "history": [[p, v, float(o)] for p, v, o in history]}
    atomic_write_json(path, doc)
    return path


def mode_name(kind: str, use_mag: bool) -> str:
    """The ``gains.json`` key (a ``MODES`` name) of a learned filter kind in 9D or 6D."""
    return next(m for m, (k, nine) in MODES.items() if k == kind and nine == use_mag)


def load_gains(model_dir, use_mag: bool = True, kind: str = "toggling"):
    """The learned settings stored by ``save_gains`` for filter ``kind`` (``"toggling"`` or
    ``"vqf_toggling"``) in 9D or 6D; refuses gains learned for other models."""
    model_dir = Path(model_dir)
    path = model_dir / GAINS_FILE
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no learned gains; run `togglecf train` (it learns them after the models)")
    doc = json.loads(path.read_text())
    check_gains_format(doc, path)
    meta = json.loads((model_dir / "metadata.json").read_text())
    if doc.get("feature_schema_hash") != meta["feature_schema"]["hash"]:
        raise ValueError(f"{path}: gains were learned for models with another feature schema")
    if kind not in _SETTINGS_OF:
        raise ValueError(f"unknown learned filter {kind!r}; one of {sorted(_SETTINGS_OF)}")
    key = mode_name(kind, use_mag)
    if key not in doc:
        have = sorted(k for k in doc if k in MODES)
        raise KeyError(f"{path}: no gains of mode {key!r} stored (have: {have}); learn them with "
                       f"`togglecf train` and [gains] modes = [..., \"{key}\"]")
    return settings_from_dict(_SETTINGS_OF[kind], doc[key]["settings"])


def settings_from_dict(cls, d: dict):
    """A learned filter's settings ``cls`` from their stored JSON form (lists for tuples); a field
    the file does not store takes its default (a learned VQF stored before ``mag_backoff_measured``
    existed backs off on the predicted disturbance, now bounded by the core's rejection factor)."""
    return cls(**{k: tuple(v) if isinstance(v, list) else v for k, v in d.items()})


def check_gains_format(doc: dict, path) -> None:
    """Refuse a ``gains.json`` that is not of ``GAINS_FORMAT`` (the old one, without a ``format``
    key, holds per-sample gains valid only at the rate they were learned at)."""
    fmt = doc.get("format")
    if fmt == GAINS_FORMAT:
        return
    what = ("has no \"format\" key: it is the old format (per-sample gains, valid only at the rate they were "
            "learned at)") if fmt is None else f"has format {fmt!r}, this togglecf reads format {GAINS_FORMAT}"
    raise ValueError(f"{path} {what}. The gains are now time constants in seconds: retrain this model directory "
                     f"with `togglecf train` (it writes gains.json format {GAINS_FORMAT})")


class LearnedGains(NamedTuple):
    """The gains of one mode as ``learn_and_save_gains`` learned and stored them."""

    settings: object  # TogglingSettings or VQFTogglingSettings (time constants in s), as ``load_gains`` reads them
    history: list  # the descent's (parameter, value, objective) steps, as ``gains.json`` "history" holds them


def learn_and_save_gains(model_dir, trials, search: GainSearch, modes=("9d", "6d"), jobs: int = 1, log=None,
                         predictions=None, vqf_search: VQFGainSearch | None = None,
                         models: CompiledModels | None = None) -> dict:
    """After ``togglecf train``: learn the gains of each mode on the training ``trials`` and store
    them in ``model_dir/gains.json``. Returns mode -> ``LearnedGains``. ``models``: the directory's
    models when the caller holds them (else read back from ``model_dir``).

    ``predictions``: per-trial ``(N, S + 6)`` *out-of-fold* predictions (from the CV models, which
    never saw that trial). Without them the final models' in-sample predictions are used; they are
    over-confident (the regressors look near-perfect on their own training data), so gains learned
    on them trust the models too much: the study measured it (see README)."""
    models = models if models is not None else CompiledModels.from_bundle(load_bundle(model_dir))
    source = "out-of-fold (CV models that never saw the trial)" if predictions is not None else "in-sample"
    preds = predictions if predictions is not None else [models.predict_samples(t.gyr, t.acc, t.mag, t.fs)
                                                          for t in trials]
    out = {}
    for mode, settings, hist, mode_search in learn_modes(trials, preds, models, modes, search, vqf_search, jobs, log,
                                                         source):
        save_gains(model_dir, settings, trials, hist, use_mag=MODES[mode][1], predictions=source, search=mode_search)
        out[mode] = LearnedGains(settings, hist)
    return out


def learn_modes(trials, predictions, models: CompiledModels, modes, search: GainSearch | None = None,
                vqf_search: VQFGainSearch | None = None, jobs: int = 1, log=None, source: str = ""):
    """The coordinate descent (``learn_gains``) of each gain mode of ``modes`` (``MODES``) on
    ``trials`` with the per-trial ``predictions`` of ``models``: yields ``(mode, settings, history,
    search)`` per mode as it finishes (``search``: the ``GainSearch`` of the toggling CF's modes or
    the ``VQFGainSearch`` of the learned VQF's), each logged in one line (``source``: where the
    predictions come from). ``togglecf train`` and the re-tuning of the pretrained model both learn
    their gains here."""
    log = log or logger.info  # progress: the togglecf logger (stderr) unless a caller passes its own
    for mode in modes:
        if mode not in MODES:
            raise ValueError(f"gain mode must be one of {list(MODES)}, got {mode!r}")
        kind, use_mag = MODES[mode]
        t0 = time.perf_counter()
        mode_search = (search or GainSearch()) if kind == "toggling" else (vqf_search or VQFGainSearch())
        settings, hist = learn_gains(trials, predictions, models.class_names, models.static_state, use_mag=use_mag,
                                     search=mode_search, jobs=jobs)
        log(f"gains {mode} ({source} predictions): {mode_search.objective} on the training trials "
            f"{hist[0][2]:.4f} -> {hist[-1][2]:.4f} in {time.perf_counter() - t0:.0f} s: {describe_gains(settings)}")
        yield mode, settings, hist, mode_search


def describe_gains(settings) -> str:
    """The learned values of ``settings`` in one line (logs, reports)."""
    if isinstance(settings, VQFTogglingSettings):
        return (f"τ_acc {settings.tau_acc_states} s, τ_mag {settings.tau_mag_states} s, σ_motion "
                f"{settings.bias_sigma_motion_states} °/s, rest th_ω {settings.rest_th_gyr_states} °/s, th_a "
                f"{settings.rest_th_acc_states} m/s², c₀ {settings.confidence_floor}, σ_m "
                f"{settings.mag_disturbance_scale} µT, noise weights {settings.noise_weight_acc}/"
                f"{settings.noise_weight_mag}, modulation τ {settings.modulation_tau} s"
                + (f", field change σ_f {settings.field_change_scale} µT (τ_f {settings.field_change_tau} s)"
                   if settings.field_change_scale > 0.0 else ""))
    return (f"τ_acc {settings.tau_acc} s, τ_mag {settings.tau_mag} s, output τ {settings.output_tau} s, "
            f"bias τ {settings.bias_tau} s, σ_m {settings.mag_disturbance_scale} µT, noise weights "
            f"{settings.noise_weight_acc}/{settings.noise_weight_mag}, c₀ {settings.confidence_floor}, "
            f"heading rate bound {settings.mag_rate_limit} rad/s")
