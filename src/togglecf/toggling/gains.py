"""Learning the toggling filter's gains on training trials (coordinate descent on BROAD RMSE).

The models' predictions do not depend on the gains, so they are computed once per trial
(``CompiledModels.predict_samples``) and every candidate setting only re-runs the cheap
filter core. The objective is BROAD's: the mean total RMSE over the given trials (6D: with
the constant heading offset removed). Each parameter is searched on its own grid while the
others are held; a few sweeps over all parameters converge on these smooth objectives.
"""
from __future__ import annotations

import json
import logging
import math
import multiprocessing as mp
import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np
from numba import njit

from togglecf.core.io import atomic_write_json, check_keys
from togglecf.core.progress import progress
from togglecf.filters.toggling import TogglingFilter, TogglingSettings
from togglecf.learn.compiled import CompiledModels
from togglecf.learn.models import load_bundle
from togglecf.metrics.broad import error_angles_rad, error_quaternion, remove_heading_offset, rmse_deg

__all__ = ["GainSearch", "learn_gains", "mean_total_rmse", "save_gains", "load_gains", "learn_and_save_gains", "GAINS_FILE"]

logger = logging.getLogger(__name__)

_ALPHA_GRID = (0.0, 0.00003, 0.0001, 0.0002, 0.0005, 0.001, 0.002, 0.005, 0.01, 0.02, 0.05)


@dataclass(frozen=True)
class GainSearch:
    """Grids of the coordinate descent (gains per sample at the data's rate; σ_m in µT).

    Attributes:
        alpha: grid of every per-state acc and mag gain.
        gamma: grid of the output blend weight.
        bias_gain: grid of the rest-bias low-pass gain.
        bias_gate: grid of the largest |ω − b| [rad/s] taken as bias.
        mag_disturbance_scale: grid of σ_m (0 = off).
        noise_weight_acc, noise_weight_mag: grids of the weights of the predicted noise.
        sweeps: passes over all parameters.
    """

    alpha: tuple = _ALPHA_GRID
    gamma: tuple = (0.3, 0.6, 1.0)
    bias_gain: tuple = (0.0, 0.0003, 0.001, 0.003)
    bias_gate: tuple = (0.02, 0.05)
    mag_disturbance_scale: tuple = (0.0, 3.0, 10.0, 30.0)
    noise_weight_acc: tuple = (0.0, 0.5, 1.0)
    noise_weight_mag: tuple = (0.0, 0.5, 1.0)
    sweeps: int = 2

    @classmethod
    def from_dict(cls, d: dict) -> "GainSearch":
        return cls(**{k: tuple(float(x) for x in v) if isinstance(v, (list, tuple)) else v
                      for k, v in check_keys(cls, d, "gain-search").items()})


def _trial_total(t, pred, settings, use_mag) -> float:
    f = TogglingFilter(t.fs, settings, use_mag=use_mag)
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


def mean_total_rmse(settings: TogglingSettings, trials, predictions, use_mag: bool = True, pool=None) -> float:
    """Mean over trials of BROAD's total RMSE [deg] of the toggling filter with ``settings``.
    ``pool``: an ``_TrialPool`` (from ``learn_gains``) to spread the trials over processes."""
    if pool is not None:
        return float(np.mean(pool.map(settings, use_mag)))
    return float(np.mean([_trial_total(t, p, settings, use_mag) for t, p in zip(trials, predictions)]))


_WORK = {}


def _pool_task(i, settings, use_mag):
    t, p = _WORK["trials"][i], _WORK["predictions"][i]
    return _trial_total(t, p, settings, use_mag)


class _TrialPool:
    """Fork workers that inherit the trials and predictions (nothing large is pickled)."""

    def __init__(self, trials, predictions, jobs):

        _WORK["trials"], _WORK["predictions"] = list(trials), list(predictions)
        TogglingFilter(100.0).update_batch(np.zeros((2, 3)), np.ones((2, 3)), np.ones((2, 3)))  # compile first
        self.n = len(trials)
        self.ex = ProcessPoolExecutor(jobs, mp_context=mp.get_context("fork"))

    def map(self, settings, use_mag):
        return list(self.ex.map(_pool_task, range(self.n), [settings] * self.n, [use_mag] * self.n))

    def close(self):
        self.ex.shutdown()
        _WORK.clear()


def _candidates(settings: TogglingSettings, search: GainSearch):
    """(label, list of settings) for each coordinate."""
    n = len(settings.states)
    for name in ("alpha_acc", "alpha_mag"):
        for s in range(n):
            vals = []
            for a in search.alpha:
                g = list(getattr(settings, name))
                g[s] = a
                vals.append((a, {name: tuple(g)}))
            yield f"{name}[{settings.states[s]}]", vals
    for name in ("noise_weight_acc", "noise_weight_mag", "gamma", "bias_gain", "bias_gate", "mag_disturbance_scale"):
        yield name, [(v, {name: v}) for v in getattr(search, name)]


def learn_gains(trials, predictions, states, static_state, use_mag: bool = True, search: GainSearch | None = None,
                start: TogglingSettings | None = None, verbose: bool = False, jobs: int = 1):
    """Coordinate descent from ``start`` (default: moderate gains). Returns ``(settings, history)``
    with ``history`` a list of ``(parameter, value, objective)`` after each accepted step.
    ``jobs > 1`` spreads the trials over that many forked processes."""

    # a daemonic process (a Dask worker, a pool worker) may not fork a pool: evaluate in-process there
    parallel = jobs > 1 and len(trials) > 1 and not mp.current_process().daemon
    pool = _TrialPool(trials, predictions, jobs) if parallel else None
    try:
        return _descend(trials, predictions, states, static_state, use_mag, search, start, verbose, pool)
    finally:
        if pool is not None:
            pool.close()


def _descend(trials, predictions, states, static_state, use_mag, search, start, verbose, pool):
    search = search or GainSearch()
    n = len(states)
    settings = start or TogglingSettings(states=tuple(states), static_state=static_state,
                                         alpha_acc=(0.001,) * n, alpha_mag=(0.0003,) * n, gamma=1.0, bias_gain=0.001)
    if not use_mag:
        search = replace(search, mag_disturbance_scale=(settings.mag_disturbance_scale,))
    best = mean_total_rmse(settings, trials, predictions, use_mag, pool)
    history = [("start", None, best)]
    coords = list(_candidates(settings, search))
    for sweep in range(search.sweeps):
        improved = False
        for label, _ in progress(coords, desc=f"gains sweep {sweep + 1}", unit="param"):
            if not use_mag and label.startswith("alpha_mag"):
                continue
            cands = dict(_candidates(settings, search))[label]  # rebuilt from the current settings
            for value, change in cands:
                trial_settings = replace(settings, **change)
                if trial_settings == settings:
                    continue
                obj = mean_total_rmse(trial_settings, trials, predictions, use_mag, pool)
                if obj < best - 1e-9:
                    best, settings, improved = obj, trial_settings, True
                    history.append((label, value, obj))
            if verbose:
                logger.info(f"  {label}: {best:.4f}°")
        if not improved:
            break
    return settings, history


GAINS_FILE = "gains.json"


def save_gains(model_dir, settings: TogglingSettings, trials, history, use_mag: bool = True,
               predictions: str = "in-sample"):
    """Write ``gains.json`` beside the models (atomically): the learned settings, the trials
    they were learned on, the objective history and the models' schema hash they belong to."""
    model_dir = Path(model_dir)
    meta = json.loads((model_dir / "metadata.json").read_text())
    key = "9d" if use_mag else "6d"
    path = model_dir / GAINS_FILE
    doc = json.loads(path.read_text()) if path.is_file() else {}
    doc["feature_schema_hash"] = meta["feature_schema"]["hash"]
    doc[key] = {"settings": asdict(settings), "trials": [getattr(t, "name", t) for t in trials],
                "objective": "mean total RMSE [deg] over the trials (BROAD)", "predictions": predictions,
                "history": [[p, v, float(o)] for p, v, o in history]}
    atomic_write_json(path, doc)
    return path


def load_gains(model_dir, use_mag: bool = True) -> TogglingSettings:
    """The learned settings stored by ``save_gains``; refuses gains learned for other models."""
    model_dir = Path(model_dir)
    path = model_dir / GAINS_FILE
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no learned gains; run `togglecf train` (it learns them after the models)")
    doc = json.loads(path.read_text())
    meta = json.loads((model_dir / "metadata.json").read_text())
    if doc.get("feature_schema_hash") != meta["feature_schema"]["hash"]:
        raise ValueError(f"{path}: gains were learned for models with another feature schema")
    key = "9d" if use_mag else "6d"
    if key not in doc:
        raise KeyError(f"{path}: no {key.upper()} gains stored (have: {sorted(k for k in doc if k in ('9d', '6d'))})")
    s = dict(doc[key]["settings"])
    for k in ("states", "alpha_acc", "alpha_mag"):
        s[k] = tuple(s[k])
    return TogglingSettings(**s)


def learn_and_save_gains(model_dir, trials, search: GainSearch, modes=("9d", "6d"), jobs: int = 1, log=None,
                         predictions=None) -> dict:
    """After ``togglecf train``: learn the gains of each mode on the training ``trials`` and store
    them in ``model_dir/gains.json``. Returns mode -> settings.

    ``predictions``: per-trial ``(N, S + 6)`` *out-of-fold* predictions (from the CV models, which
    never saw that trial). Without them the final models' in-sample predictions are used; they are
    over-confident (the regressors look near-perfect on their own training data), so gains learned
    on them trust the models too much: the study measured it (see README)."""
    models = CompiledModels.from_bundle(load_bundle(model_dir))
    log = log or logger.info  # progress: the togglecf logger (stderr) unless a caller passes its own
    source = "out-of-fold (CV models that never saw the trial)" if predictions is not None else "in-sample"
    preds = predictions if predictions is not None else [models.predict_samples(t.gyr, t.acc, t.mag, t.fs)
                                                          for t in trials]
    out = {}
    for mode in modes:
        if mode not in ("9d", "6d"):
            raise ValueError(f"gain mode must be '9d' or '6d', got {mode!r}")
        t0 = time.perf_counter()
        settings, hist = learn_gains(trials, preds, models.class_names, models.static_state, use_mag=mode == "9d",
                                     search=search, jobs=jobs)
        save_gains(model_dir, settings, trials, hist, use_mag=mode == "9d", predictions=source)
        log(f"gains {mode.upper()} ({source} predictions): mean total RMSE on the training trials {hist[0][2]:.3f}° -> {hist[-1][2]:.3f}° "
            f"in {time.perf_counter() - t0:.0f} s: acc {settings.alpha_acc}, mag {settings.alpha_mag}, "
            f"gamma {settings.gamma}, bias {settings.bias_gain}, σ_m {settings.mag_disturbance_scale}, "
            f"noise weights {settings.noise_weight_acc}/{settings.noise_weight_mag}")
        out[mode] = settings
    return out
