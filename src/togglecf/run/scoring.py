"""Running one filter on trials and scoring it with BROAD's metrics: the one loop that
``evaluate``/``tune`` (through ``run.sweep``), the held-out study and the pruning sweep use.
"""
from __future__ import annotations

import itertools
import time
from dataclasses import dataclass, field

import numpy as np

from togglecf.data.broad import Trial
from togglecf.filters import FilterOutput, dt_from_timestamps
from togglecf.metrics.broad import ErrorReference
from togglecf.registry import FilterSpec

__all__ = ["TrialResult", "run_built", "run_filter", "score_trial", "score_trials", "warm_up", "grid_points",
           "parse_grid"]


@dataclass
class TrialResult:
    """Scores of one filter on one trial: BROAD RMSEs [deg] and speed [µs per sample]; ``diagnostics``:
    run summaries of a learned filter (``fallback``: fraction of the scored samples whose held
    prediction was refused as out of the training range, ``learn.ranges``)."""

    trial: str
    groups: tuple
    errors: dict
    us_per_sample: float
    n_samples: int
    params: dict = field(default_factory=dict)
    diagnostics: dict = field(default_factory=dict)


_WARM: set = set()


#: Hz; the kernels compile the same at any rate: this one only triggers compilation
_COMPILE_FS = 100.0


def warm_up(spec: FilterSpec, fs: float = _COMPILE_FS):
    """Compile the spec's kernels on a few samples, once per process, so that timing excludes JIT
    compilation (and, before a process pool forks, so that workers inherit compiled code)."""
    key = (spec.name, spec.use_mag, spec.models)
    if key in _WARM:
        return
    f = spec.build(fs)
    z = np.tile([[0.0, 0.0, 9.81]], (4, 1))
    f.update_batch(z * 0.0, z, z + [20.0, 0.0, 0.0] if spec.use_mag else None)
    _WARM.add(key)


def run_filter(trial: Trial, spec: FilterSpec) -> tuple[FilterOutput, float]:
    """Run a freshly built filter over a whole trial, with the per-sample Δt of its time stamps when it
    has them (``Trial.time``, an imported log), else at its nominal rate. Returns ``(FilterOutput, µs
    per sample)``."""
    f = spec.build(trial.fs)
    warm_up(spec, trial.fs)
    return _timed_run(f, trial, spec.use_mag)


def run_built(trial: Trial, build, use_mag: bool = True) -> tuple[FilterOutput, float]:
    """``run_filter`` for a filter no ``FilterSpec`` names (e.g. trained models held in memory): ``build(fs)``
    makes it (rate [Hz]); a first one runs a few samples so that timing excludes JIT compilation."""
    f = build(trial.fs)
    z = np.tile([[0.0, 0.0, 9.81]], (4, 1))
    build(_COMPILE_FS).update_batch(z * 0.0, z, z + [20.0, 0.0, 0.0] if use_mag else None)
    return _timed_run(f, trial, use_mag)


def _timed_run(f, trial: Trial, use_mag: bool) -> tuple[FilterOutput, float]:
    """The filter ``f`` over the whole ``trial`` (time-stamp Δt when it has them) and µs per sample."""
    dt = None if trial.time is None else dt_from_timestamps(trial.time)
    t0 = time.perf_counter()
    out = f.update_batch(trial.gyr, trial.acc, trial.mag if use_mag else None, dt=dt)
    return out, 1e6 * (time.perf_counter() - t0) / trial.n_samples


def score_trial(trial: Trial, spec: FilterSpec,
                reference: ErrorReference | None = None) -> tuple[TrialResult, FilterOutput]:
    """BROAD's errors of ``spec`` on ``trial`` (6D: heading offset removed) and the output itself;
    ``reference``: the trial's ``ErrorReference`` when the caller scores it many times (a grid)."""
    out, us = run_filter(trial, spec)
    reference = reference or ErrorReference(trial.opt_quat, trial.movement)
    errs = reference.errors(out.quat, six_d=not spec.use_mag)
    return TrialResult(trial.name, trial.groups, errs, us, trial.n_samples, spec.as_params(),
                       run_diagnostics(out, trial)), out


def run_diagnostics(out: FilterOutput, trial: Trial) -> dict:
    """Summaries of a run over the samples BROAD scores (``movement``), for the diagnostics a filter
    has: the share of samples whose window was out of the models' training range (``fallback``: a
    filter with its models in the loop) and the share that fell back for low confidence
    (``low_confidence``: the toggling CF's confidence floor); empty for other filters."""
    scored = np.asarray(trial.movement, bool)
    shares = {}
    for key in ("fallback", "low_confidence"):
        if key in out.diagnostics:
            v = np.asarray(out.diagnostics[key])[scored]
            shares[key] = float(v.mean()) if v.size else float("nan")
    return shares


def score_trials(trials, spec: FilterSpec) -> list[tuple[TrialResult, FilterOutput]]:
    """``score_trial`` over ``trials`` in order (a fold's test trials, one filter)."""
    return [score_trial(t, spec) for t in trials]


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
