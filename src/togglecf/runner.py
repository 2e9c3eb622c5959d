"""Run filters on BROAD trials and score them: one trial, a set of trials in parallel, a grid.

Work is split by trial over a process pool (``jobs`` workers, default all cores); each
worker loads its trial from disk itself, so arrays are not shipped between processes.
"""
from __future__ import annotations

import itertools
import os
import time
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import dataclass, field
import multiprocessing as mp

import numpy as np

from .data import Trial, load_trial
from .evaluation import TagpResult, tagp, trial_errors
from .filters import make_filter
from .progress import progress

__all__ = ["TrialResult", "run_filter", "evaluate_trials", "grid_points", "grid_search", "parse_grid"]


@dataclass
class TrialResult:
    """Scores of one filter on one trial: BROAD RMSEs [deg] and speed [µs per sample]."""

    trial: str
    groups: tuple
    errors: dict
    us_per_sample: float
    n_samples: int
    params: dict = field(default_factory=dict)


def build_filter(filter_name: str, fs: float, params: dict, use_mag: bool = True):
    """A filter by CLI name; ``toggling`` takes ``params={"models": DIR}`` (models + learned gains)."""
    if filter_name == TOGGLING:
        if set(params) != {"models"}:
            raise ValueError("the toggling filter takes its models and learned gains from --models DIR, no --param")
        from .filters.toggling import load_toggling_filter

        return load_toggling_filter(params["models"], fs, use_mag=use_mag)
    return make_filter(filter_name, fs, use_mag=use_mag, **params)


TOGGLING = "toggling"


def run_filter(trial: Trial, filter_name: str, params: dict, use_mag: bool = True):
    """Run a filter on a trial. Returns ``(FilterOutput, µs per sample)``."""
    f = build_filter(filter_name, trial.fs, params, use_mag)
    _warm_up(filter_name, trial.fs, use_mag, params)
    t0 = time.perf_counter()
    out = f.update_batch(trial.gyr, trial.acc, trial.mag if use_mag else None)
    elapsed = time.perf_counter() - t0
    return out, 1e6 * elapsed / trial.n_samples


_WARM = set()


def _warm_up(filter_name, fs, use_mag, params):
    """Compile the kernels on a few samples so that timing excludes JIT compilation."""
    key = (filter_name, use_mag)
    if key in _WARM:
        return
    f = build_filter(filter_name, fs, params, use_mag)
    z = np.tile([[0.0, 0.0, 9.81]], (4, 1))
    f.update_batch(z * 0.0, z, z + [20.0, 0.0, 0.0] if use_mag else None)
    _WARM.add(key)


def _score(trial: Trial, filter_name, params, use_mag) -> TrialResult:
    out, us = run_filter(trial, filter_name, params, use_mag)
    errs = trial_errors(out.quat, trial.opt_quat, trial.movement, six_d=not use_mag)
    return TrialResult(trial.name, trial.groups, errs, us, trial.n_samples, dict(params))


def _evaluate_one(path, groups, filter_name, params_list, use_mag):
    trial = load_trial(path, groups=groups)
    return [_score(trial, filter_name, p, use_mag) for p in params_list]


def _pool(jobs):
    # fork: workers inherit the parent's compiled kernels (compiled in _warm_up before the pool)
    return ProcessPoolExecutor(max_workers=jobs, mp_context=mp.get_context("fork"))


def evaluate_trials(index, names, filter_name, params_list, use_mag=True, jobs=None, desc="evaluate"):
    """Evaluate every parameter dict in ``params_list`` on every named trial of ``index``.

    Returns a list (one per ``params_list`` entry) of dicts trial -> TrialResult, in the
    order of ``names``. ``jobs=1`` runs in this process (easier to debug and profile).
    """
    jobs = jobs or os.cpu_count() or 1
    _warm_up(filter_name, 285.0, use_mag, params_list[0])
    per_trial = {}
    tasks = [(index.available[n], index.trial_groups(n)) for n in names]
    if jobs == 1 or len(names) == 1:
        for name, (path, groups) in progress(list(zip(names, tasks)), desc=desc, unit="trial"):
            per_trial[name] = _evaluate_one(path, groups, filter_name, params_list, use_mag)
    else:
        with _pool(min(jobs, len(names))) as pool:
            futs = {pool.submit(_evaluate_one, p, g, filter_name, params_list, use_mag): n
                    for n, (p, g) in zip(names, tasks)}
            for fut in progress(as_completed(futs), total=len(futs), desc=desc, unit="trial"):
                per_trial[futs[fut]] = fut.result()
    return [{n: per_trial[n][i] for n in names} for i in range(len(params_list))]


def parse_grid(specs: list[str]) -> dict[str, list[float]]:
    """``["alpha=0.001:0.02:0.001", "k=1,2,3", "b=0.5"]`` -> name -> list of values.

    ``start:stop:step`` includes ``stop`` (BROAD's grids do); values are rounded to 10
    decimals so that grid points print and compare cleanly.
    """
    grid = {}
    for spec in specs:
        if "=" not in spec:
            raise ValueError(f"grid/parameter {spec!r}: expected name=value, name=a,b,c or name=start:stop:step")
        name, val = (s.strip() for s in spec.split("=", 1))
        try:
            if ":" in val:
                start, stop, step = (float(x) for x in val.split(":"))
                if step <= 0 or stop < start:
                    raise ValueError
                n = int(np.floor((stop - start) / step + 1e-9)) + 1
                values = [round(start + i * step, 10) for i in range(n)]
            else:
                values = [float(x) for x in val.split(",")]
        except ValueError:
            raise ValueError(f"grid/parameter {spec!r}: cannot parse {val!r}") from None
        grid[name] = values
    return grid


def grid_points(grid: dict) -> list[dict]:
    """Every parameter dict of a grid (name -> values), in ``itertools.product`` order."""
    return [dict(zip(grid, k)) for k in itertools.product(*grid.values())]


def grid_search(index, names, filter_name, grid, use_mag=True, jobs=None) -> TagpResult:
    """Evaluate the full grid on the trials and return BROAD's TAGP (see ``evaluation.tagp``)."""
    params_list = grid_points(grid)
    keys = [tuple(p.values()) for p in params_list]
    results = evaluate_trials(index, names, filter_name, params_list, use_mag, jobs, desc=f"tune {filter_name}")
    scored = {k: {n: r.errors for n, r in res.items()} for k, res in zip(keys, results)}
    return tagp(grid, scored)
