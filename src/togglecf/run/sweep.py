"""Filter sweeps (``evaluate``, ``tune``) on any backend, streamed to a resumable journal.

A sweep is every parameter dict of a list on every named trial. Tasks are (trial, chunk of
parameter dicts); each loads its trial where it runs (from the data directory's path, which the
workers must be able to read; all of them for an index over several directories) and returns one
``TrialResult`` per parameter dict.

Journal (``ResultStore``, JSON lines, one line per (trial, parameter dict), flushed after every
finished task): each result is keyed by the filter, 6D/9D, the parameters, the trial, the trial
file's identity (name, size, mtime) and the code version (and for the toggling filter the model
files' identities). A second run with the same journal computes only the points that are not in
it; a changed file, filter setting or version computes anew. Floats are written with ``repr``, so
resumed results are bit-identical to computed ones.

Failures: a trial that cannot be loaded or evaluated (missing on a worker, corrupt file, too short,
too many non-finite samples: ``data.broad.load_trial``, ``check_evaluable``) or a task that fails after its retries
becomes a failure record (trial -> error message, a ``DataError``'s naming file, field and problem);
the other tasks go on. The points it leaves out are listed in ``SweepResult.missing``;
``format_failures`` gives one line per failed trial. Non-finite IMU samples of the trials that were
evaluated are counted in ``SweepResult.invalid`` (trial -> counts per field and in total).
"""
from __future__ import annotations

import hashlib
import json
import math
import os
from dataclasses import dataclass, field
from pathlib import Path

from togglecf import __version__
from togglecf.data.broad import DataError, check_evaluable
from togglecf.metrics.broad import ErrorReference, TagpResult, tagp
from togglecf.parallel.backend import Backend, LocalBackend, data_location, load_trial_cached, trial_identity
from togglecf.registry import filter_spec
from togglecf.run.scoring import TrialResult, grid_points, score_trial, warm_up

__all__ = ["ResultStore", "SweepResult", "run_sweep", "evaluate_trials", "grid_search", "SWEEP_VERSION", "journal_path",
           "format_failures"]

SWEEP_VERSION = f"togglecf-{__version__}/sweep-1"
JOURNAL = "sweep.jsonl"


def journal_path(out_dir) -> Path:
    return Path(out_dir) / JOURNAL


def point_key(filter_name, use_mag, params: dict, trial_id: str, extra=None) -> str:
    blob = json.dumps([SWEEP_VERSION, filter_name, bool(use_mag), sorted(params.items()), trial_id, extra],
                      default=str)
    return hashlib.sha256(blob.encode()).hexdigest()


class ResultStore:
    """Append-only JSONL journal of sweep results (see the module doc). A record counts as done
    when it has a ``key`` and every field of ``required`` (a line cut by an interruption is skipped);
    ``done`` maps key -> record. The pruning sweep keeps its points in one too."""

    def __init__(self, path, fresh: bool = False, required=("errors",)):
        self.path = Path(path)
        self.required = tuple(required)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        if fresh:
            self.path.unlink(missing_ok=True)
        self.done = {}
        if self.path.exists():
            with open(self.path, encoding="utf-8") as f:
                for line in f:
                    try:
                        rec = json.loads(line)
                    except ValueError:  # a line cut by an interruption
                        continue
                    if self._complete(rec):
                        self.done[rec["key"]] = rec
        self._f = open(self.path, "a", encoding="utf-8")

    def _complete(self, rec) -> bool:
        return isinstance(rec, dict) and "key" in rec and all(k in rec for k in self.required)

    def write(self, records):
        for rec in records:
            self._f.write(json.dumps(rec) + "\n")
            if self._complete(rec):
                self.done[rec["key"]] = rec
        self._f.flush()
        os.fsync(self._f.fileno())

    def close(self):
        self._f.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


@dataclass
class SweepResult:
    """``results[i]``: trial -> TrialResult for ``params_list[i]`` (trials in the given order, failed
    trials absent); ``failed``: trial -> error message; ``missing``: (trial, params) not computed;
    ``invalid``: trial -> ``{"gyr": k, "acc": k, "mag": k, "samples": k}`` non-finite IMU samples
    (``samples``: with any field bad) of the evaluated trials (absent for results resumed from a
    journal written before the counts were recorded)."""

    results: list
    failed: dict = field(default_factory=dict)
    missing: list = field(default_factory=list)
    computed: int = 0
    reused: int = 0
    invalid: dict = field(default_factory=dict)


def _error_text(exc) -> str:
    """A ``DataError`` names file, field and problem already; other errors get their type."""
    return str(exc) if isinstance(exc, DataError) else f"{type(exc).__name__}: {exc}"


def format_failures(failed: dict, files: dict | None = None) -> list[str]:
    """One line per failed trial (``failed``: trial -> message), starting with the trial's file
    (``files``: trial -> path) unless the message already does."""
    lines = []
    for name, msg in failed.items():
        where = str(files.get(name, name)) if files else name
        lines.append(str(msg) if str(msg).startswith(where) else f"{where}: {msg}")
    return lines


def _sweep_task(root, name, filter_name, params_list, use_mag):
    try:
        trial = check_evaluable(load_trial_cached(root, name))
    except Exception as exc:  # reported as a failed trial; the sweep goes on
        return {"load_error": _error_text(exc)}
    invalid = {**trial.invalid, "samples": trial.n_invalid}
    reference = ErrorReference(trial.opt_quat, trial.movement)  # once for all the task's points
    return {"results": [score_trial(trial, filter_spec(filter_name, p, use_mag), reference)[0] for p in params_list],
            "invalid": invalid}


def _chunks(n_points, n_trials, workers, chunk_size):
    if n_points == 0:
        return []
    if chunk_size is None:
        chunk_size = n_points  # one task per trial
    elif chunk_size <= 0:  # auto: >= 4 tasks per worker, at most 64 points per task
        per_trial = max(1, math.ceil(4 * workers / max(1, n_trials)))
        chunk_size = min(64, max(1, math.ceil(n_points / per_trial)))
    return [range(i, min(i + chunk_size, n_points)) for i in range(0, n_points, chunk_size)]


def run_sweep(index, names, filter_name, params_list, use_mag=True, backend: Backend | None = None,
              store: ResultStore | None = None, chunk_size: int | None = None, on_error="report",
              on_result=None) -> SweepResult:
    """Evaluate every dict of ``params_list`` on every trial of ``names`` (see the module doc).

    ``chunk_size``: parameter dicts per task (``None``: all, one task per trial; ``0``: automatic).
    ``on_error``: ``"raise"`` re-raises the first failure, ``"report"`` records it and goes on.
    ``on_result(n_done)`` is called after each finished task (progress hooks, tests).
    """
    backend = backend or LocalBackend()
    specs = [filter_spec(filter_name, p, use_mag) for p in params_list]  # validated here, before any worker starts
    root = data_location(index)  # one directory, or the tuple of a MultiIndex's
    extra = specs[0].identity() if specs else None
    ids = {n: trial_identity(index.available[n]) for n in names}
    keys = {(n, i): point_key(filter_name, use_mag, p, ids[n], extra) for n in names for i, p in enumerate(params_list)}
    got, invalid = {}, {}
    reused = 0
    if store is not None:
        for nk, k in keys.items():
            if k in store.done:
                rec = store.done[k]
                # the trial's name and groups in this index (a file keeps its key under "<dataset>/" names)
                got[nk] = TrialResult(nk[0], index.trial_groups(nk[0]), rec["errors"], rec["us_per_sample"],
                                      rec["n_samples"], dict(params_list[nk[1]]), rec.get("diagnostics", {}))
                if rec.get("invalid") is not None:
                    invalid[nk[0]] = rec["invalid"]
        reused = len(got)
    tasks = []
    for n in names:
        todo = [i for i in range(len(params_list)) if (n, i) not in got]
        for ch in _chunks(len(todo), len(names), backend.workers, chunk_size):
            idx = [todo[j] for j in ch]
            tasks.append(((n, idx), (root, n, filter_name, [params_list[i] for i in idx], use_mag)))
    if tasks and isinstance(backend, LocalBackend):
        warm_up(specs[0])  # compiled before the fork
    failed, computed = {}, 0
    desc = f"{filter_name} ({'9D' if use_mag else '6D'}, {len(params_list)} point{'s' if len(params_list) != 1 else ''})"
    for done, out in enumerate(backend.run(_sweep_task, tasks, desc=desc, unit="task"), 1):
        name, idx = out.key
        if out.error is not None or "load_error" in out.value:
            msg = out.value["load_error"] if out.error is None else _error_text(out.error)
            if on_error == "raise":
                if out.error is not None:
                    raise out.error
                raise RuntimeError(f"{name}: {msg}")
            failed.setdefault(name, msg)
            if store is not None:
                store.write([{"failed": name, "error": msg, "params": [params_list[i] for i in idx]}])
        else:
            recs = []
            invalid[name] = out.value["invalid"]
            for i, r in zip(idx, out.value["results"]):
                got[(name, i)] = r
                recs.append({"key": keys[(name, i)], "trial": name, "filter": filter_name, "use_mag": use_mag,
                             "params": params_list[i], "trial_file": ids[name], "groups": list(r.groups),
                             "errors": r.errors, "us_per_sample": r.us_per_sample, "n_samples": r.n_samples,
                             "diagnostics": r.diagnostics, "invalid": invalid[name]})
            computed += len(idx)
            if store is not None:
                store.write(recs)
        if on_result is not None:
            on_result(done)
    results = [{n: got[(n, i)] for n in names if (n, i) in got} for i in range(len(params_list))]
    missing = [(n, params_list[i]) for n in names for i in range(len(params_list)) if (n, i) not in got]
    invalid = {n: invalid[n] for n in names if n in invalid}
    return SweepResult(results, failed, missing, computed, reused, invalid)


def evaluate_trials(index, names, filter_name, params_list, use_mag=True, jobs=None,
                    backend=None, store=None, chunk_size=None):
    """Evaluate every parameter dict in ``params_list`` on every named trial of ``index``.

    Returns a list (one per ``params_list`` entry) of dicts trial -> TrialResult, in the
    order of ``names``. ``jobs=1`` runs in this process (easier to debug and profile).
    ``backend`` (``togglecf.parallel``; default a local process pool on ``jobs`` cores), ``store``
    (a resumable ``ResultStore``) and ``chunk_size`` go to ``run_sweep``; any failed
    trial raises here (``run_sweep`` with ``on_error="report"`` reports failures instead).
    """
    backend = backend or LocalBackend(jobs)
    return run_sweep(index, names, filter_name, params_list, use_mag, backend=backend, store=store,
                     chunk_size=chunk_size, on_error="raise").results


def grid_search(index, names, filter_name, grid, use_mag=True, backend=None, store=None,
                chunk_size=None, on_error="raise", on_result=None) -> TagpResult:
    """Evaluate the full grid on the trials and return BROAD's TAGP (see ``metrics.tagp``);
    ``backend`` default: a local process pool on all cores.

    With ``on_error="report"`` a failed trial is left out of the TAGP (which needs the same trials
    at every grid point) and listed in the result's ``failed`` attribute (trial -> error)."""
    params_list = grid_points(grid)
    keys = [tuple(p.values()) for p in params_list]
    sweep = run_sweep(index, names, filter_name, params_list, use_mag, backend=backend or LocalBackend(),
                      store=store, chunk_size=chunk_size, on_error=on_error, on_result=on_result)
    complete = [n for n in names if all(n in res for res in sweep.results)]
    if not complete:
        lines = format_failures(sweep.failed, index.available)
        raise ValueError("no trial was evaluated at every grid point" + (
            f"; {len(lines)} failed:\n  " + "\n  ".join(lines) if lines else ""))
    scored = {k: {n: res[n].errors for n in complete} for k, res in zip(keys, sweep.results)}
    result = tagp(grid, scored)
    result.failed = dict(sweep.failed)
    result.incomplete = [n for n in names if n not in complete]
    result.sweep = sweep
    return result
