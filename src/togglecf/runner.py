"""Run filters on BROAD trials and score them: one trial, a set of trials in parallel, a grid.

Work is split by trial (or by trial and chunk of grid points) over a backend (``togglecf.backend``:
a local process pool of ``jobs`` workers, default all cores, or a Dask cluster); each worker loads
its trial from disk itself, so arrays are not shipped between processes (``togglecf.sweep``).
"""
from __future__ import annotations

import itertools
import time
from dataclasses import dataclass, field

import numpy as np

from .data import Trial
from .evaluation import TagpResult, tagp, trial_errors
from .filters import make_filter

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


def evaluate_trials(index, names, filter_name, params_list, use_mag=True, jobs=None, desc="evaluate",
                    backend=None, store=None, chunk_size=None):
    """Evaluate every parameter dict in ``params_list`` on every named trial of ``index``.

    Returns a list (one per ``params_list`` entry) of dicts trial -> TrialResult, in the
    order of ``names``. ``jobs=1`` runs in this process (easier to debug and profile).
    ``backend`` (``togglecf.backend``; default a local process pool on ``jobs`` cores), ``store``
    (a resumable ``sweep.ResultStore``) and ``chunk_size`` go to ``sweep.run_sweep``; any failed
    trial raises here (``run_sweep`` with ``on_error="report"`` reports failures instead).
    """
    from .backend import LocalBackend
    from .sweep import run_sweep

    backend = backend or LocalBackend(jobs)
    return run_sweep(index, names, filter_name, params_list, use_mag, backend=backend, store=store,
                     chunk_size=chunk_size, on_error="raise", desc=desc).results


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


def grid_search(index, names, filter_name, grid, use_mag=True, jobs=None, backend=None, store=None,
                chunk_size=None, on_error="raise", on_result=None) -> TagpResult:
    """Evaluate the full grid on the trials and return BROAD's TAGP (see ``evaluation.tagp``).

    With ``on_error="report"`` a failed trial is left out of the TAGP (which needs the same trials
    at every grid point) and listed in the result's ``failed`` attribute (trial -> error)."""
    from .backend import LocalBackend
    from .sweep import run_sweep

    params_list = grid_points(grid)
    keys = [tuple(p.values()) for p in params_list]
    sweep = run_sweep(index, names, filter_name, params_list, use_mag, backend=backend or LocalBackend(jobs),
                      store=store, chunk_size=chunk_size, on_error=on_error, on_result=on_result,
                      desc=f"tune {filter_name}")
    complete = [n for n in names if all(n in res for res in sweep.results)]
    if not complete:
        raise ValueError(f"no trial was evaluated at every grid point; failures: {sweep.failed}")
    scored = {k: {n: res[n].errors for n in complete} for k, res in zip(keys, sweep.results)}
    result = tagp(grid, scored)
    result.failed = dict(sweep.failed)
    result.incomplete = [n for n in names if n not in complete]
    result.sweep = sweep
    return result
