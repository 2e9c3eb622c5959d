"""Leave one dataset out: does the learning travel to a sensor, rate and lab it never saw?

For each dataset present (a directory in BROAD's layout), the models and gains are trained on all
the *other* datasets (``togglecf train``: models, then the gains on the out-of-fold predictions; the learned
VQF's with the pretrained recipe's search, ``run.config.pretrained_config``, as the model it checks) and every
trial of the dataset left out is scored:

* the learned filters (``registry.TRAINED``) with their models in the loop;
* each learned filter's **core with learning off**: for the learned VQF the VQF core at VQF's
  defaults (``vqf_core``, what it modulates), for the toggling CF the same filter at its gain
  search's starting point with every learned term off (no prediction: ``TOGGLING_CORE``);
* the classic filters of ``run.transfer.CLASSIC`` at their documented defaults, and Madgwick at its
  TAGP on the training datasets (``MADGWICK_TAGP``, BROAD's β grid of the study config): the
  reference the toggling CF must reach on data it never saw.

``lodo_table`` reports per dataset and per group, with a paired per-trial comparison of each
learned filter against its core (wins / ties / losses, Wilcoxon p): a mean can hide a trade.
"""
from __future__ import annotations

import logging
import os
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from togglecf.core.log import configured_level, follow_parent_logging
from togglecf.core.provenance import generated_line
from togglecf.data.broad import DatasetIndex, open_index
from togglecf.filters.toggling import TogglingFilter, TogglingSettings
from togglecf.metrics.broad import trial_errors
from togglecf.parallel.backend import LocalBackend, Task, run_tasks
from togglecf.registry import TOGGLING, VQF_TOGGLING, FilterSpec
from togglecf.report.study_report import TIE_DEG, paired_test
from togglecf.run.config import load_config, pretrained_config
from togglecf.run.scoring import TrialResult, score_trial
from togglecf.run.study import load_study_config
from togglecf.run.sweep import grid_search
from togglecf.run.train import run_training
from togglecf.run.transfer import models_transfer
from togglecf.toggling.gains import GainSearch
from togglecf.toggling.load import load_compiled_models

__all__ = ["TOGGLING_CORE", "MADGWICK_TAGP", "CORE_OF", "LodoPlan", "dataset_dirs", "leave_one_dataset_out",
           "plan_lodo", "toggling_core_settings", "toggling_core_results", "madgwick_tagp", "lodo_table", "lodo_json"]

log = logging.getLogger(__name__)

#: row name of the toggling CF with learning off (its gain search's start, no prediction used)
TOGGLING_CORE = "toggling_core"
#: row name of Madgwick at its TAGP on the training datasets
MADGWICK_TAGP = "madgwick_tagp"
#: each learned filter's core with learning off (the row it is compared with)
CORE_OF = {VQF_TOGGLING: "vqf_core", TOGGLING: TOGGLING_CORE}
#: rows of the tables, in order
ROWS = (VQF_TOGGLING, "vqf_core", TOGGLING, TOGGLING_CORE, MADGWICK_TAGP, "madgwick")


def dataset_dirs(first: Path) -> list[Path]:
    """``first`` and every sibling directory in BROAD's layout (a ``trials.json``), ``first``
    first, the others sorted by name: the datasets of the leave-one-dataset-out protocol."""
    first = Path(first).resolve()
    others = sorted(d for d in first.parent.iterdir() if d.is_dir() and d != first and (d / "trials.json").is_file())
    return [first, *others]


def toggling_core_settings(model_dir) -> TogglingSettings:
    """The toggling CF with learning off for the models of ``model_dir``: its gain search's starting
    point (``GainSearch.start``: moderate time constants in every state, the noise terms, the
    disturbance scale and the confidence floor off). Run it with no prediction (NaN rows) so that the
    models play no part: the filter the learned one would be without its models."""
    models = load_compiled_models(model_dir)
    return GainSearch().start(models.class_names, models.static_state)


def toggling_core_results(model_dir, index: DatasetIndex, names) -> dict:
    """trial -> ``TrialResult`` of the toggling CF with learning off (``toggling_core_settings``, no prediction)."""
    settings = toggling_core_settings(model_dir)
    out = {}
    for n in names:
        t = index.load(n)
        f = TogglingFilter(t.fs, settings)
        t0 = time.perf_counter()
        q = f.update_batch(t.gyr, t.acc, t.mag, predictions=np.full((t.n_samples, f.n_predictions), np.nan)).quat
        us = 1e6 * (time.perf_counter() - t0) / t.n_samples
        out[n] = TrialResult(t.name, t.groups, trial_errors(q, t.opt_quat, t.movement), us, t.n_samples)
    return out


def madgwick_tagp(train_dirs, jobs: int | None = None, store=None) -> dict:
    """Madgwick's TAGP (its parameters) over the study config's grid (``[baselines.madgwick]``) on
    every trial of ``train_dirs``; ``store``: a ``run.sweep.ResultStore`` that keeps the grid's results."""
    grid = load_study_config().baselines["madgwick"]
    train = open_index([str(d) for d in train_dirs])
    return grid_search(train, train.select(None), "madgwick", grid, backend=LocalBackend(jobs), store=store).params


def _scored(index: DatasetIndex, names, spec: FilterSpec) -> dict:
    return {n: score_trial(index.load(n), spec)[0] for n in names}


def _left_out(left: Path, train: list, model_dir: Path, config, verbose: bool, madgwick: dict, log_level) -> dict:
    """One left-out dataset (a task): train on ``train`` into ``model_dir``, score every trial of ``left``
    (the rows of ``ROWS`` and ``CLASSIC``; Madgwick at its TAGP ``madgwick`` on the training datasets);
    ``log_level``: the parent's (``core.log.configured_level``)."""
    follow_parent_logging(log_level)
    t0 = time.perf_counter()
    log.info(f"leave one dataset out: train on {', '.join(d.name for d in train)}; score {left.name}")
    run_training(pretrained_config(load_config(config)), data_dir=[str(d) for d in train], out=model_dir,
                 verbose=verbose)
    index = DatasetIndex.from_dir(left)
    names = index.select(None)
    per = models_transfer(model_dir, index)
    per[TOGGLING_CORE] = toggling_core_results(model_dir, index, names)
    per[MADGWICK_TAGP] = _scored(index, names, FilterSpec("madgwick", params=madgwick))
    log.info(f"  {left.name}: {len(names)} trials scored in {time.perf_counter() - t0:.0f} s (training included)")
    return per


def leave_one_dataset_out(dirs, out_dir, config=None, verbose: bool = True, jobs: int | None = None, backend=None,
                          store=None) -> dict:
    """For each directory of ``dirs`` (at least two): train on all the others into
    ``out_dir/without_<name>/models`` and score every trial of the one left out. Returns
    ``{dataset name: {filter: {trial: TrialResult}}}`` (the rows of ``ROWS`` and ``CLASSIC``).

    Madgwick's TAGP on each training set is found first, here (``store``: a ``ResultStore`` that
    keeps the grid's results, so each trial's grid is computed once over all left-out datasets);
    then the left-out datasets run as tasks on ``backend`` (default: a local process pool on
    ``jobs`` cores; with Dask the data and ``out_dir`` must be on a filesystem the workers share).
    ``plan_lodo`` runs it in parts (``make run`` runs its tasks on one pool with other steps')."""
    plan = plan_lodo(dirs, out_dir, config, verbose, jobs, store)
    # forkserver: a task trains XGBoost, whose OpenMP runtime does not survive a fork (LocalBackend)
    backend = backend or LocalBackend(min(jobs or os.cpu_count() or 1, len(plan.dirs)), start_method="forkserver")
    return plan.finish(run_tasks(backend, plan.tasks, desc="leave one dataset out", unit="dataset"))


@dataclass
class LodoPlan:
    """Leave one dataset out with Madgwick's TAGPs found and its left-out datasets ready to run
    (``plan_lodo``): ``tasks`` (``parallel.Task``, keys ``("lodo", name)``), and ``finish(done)`` for
    ``leave_one_dataset_out``'s result from their values (key -> value, as ``parallel.run_tasks`` returns them)."""

    dirs: list
    tasks: list

    def finish(self, done: dict) -> dict:
        return {d.name: done[("lodo", d.name)] for d in self.dirs}


def plan_lodo(dirs, out_dir, config=None, verbose: bool = True, jobs: int | None = None, store=None) -> LodoPlan:
    """``leave_one_dataset_out`` up to its tasks (the same arguments): Madgwick's TAGP on each training set."""
    dirs = [Path(d) for d in dirs]
    if len(dirs) < 2:
        raise ValueError(f"leave one dataset out needs at least two datasets, got {[str(d) for d in dirs]}")
    tasks = []
    for left in dirs:
        train = [d for d in dirs if d != left]
        beta = madgwick_tagp(train, jobs, store)
        log.info(f"  Madgwick's TAGP on {', '.join(d.name for d in train)}: {beta}")
        model_dir = Path(out_dir) / f"without_{left.name}" / "models"
        tasks.append(Task(("lodo", left.name), _left_out,
                          (left, train, model_dir, config, verbose, beta, configured_level())))
    return LodoPlan(dirs, tasks)


def _mean(res: dict, names) -> float:
    return float(np.mean([res[n].errors["total"] for n in names])) if names else float("nan")


def _vs_core(per: dict, learned: str, names) -> str:
    core = CORE_OF[learned]
    d = [per[learned][n].errors["total"] - per[core][n].errors["total"] for n in names]
    if len(d) < 2:
        return ""
    t = paired_test(d)
    rel = 100.0 * (_mean(per[learned], names) / _mean(per[core], names) - 1.0)
    return f"{rel:+.1f} % · {t['wins']}/{t['ties']}/{t['losses']} · p {t['p']:.2g}"


def lodo_table(results: dict, dirs, command: str, trained_on: str = "every other dataset") -> str:
    """Markdown: per left-out dataset, mean total RMSE [°] per group (all trials first) of the
    learned filters, their cores, Madgwick and VQF; for each learned filter the change against
    its core (relative mean, wins / ties / losses per trial, Wilcoxon p)."""
    by_name = {Path(d).name: Path(d) for d in dirs}
    lines = [generated_line(command), "",
             f"Each dataset is scored with models and gains trained on {trained_on} (never on it). Mean total "
             "RMSE [°] (BROAD's metric) over the trials of each group. *vs core*: the learned filter against its "
             "core with learning off (`vqf_core` = VQF's defaults for the learned VQF; `toggling_core` = the toggling "
             "CF's gain-search start with every learned term off), as the relative change of the mean, wins / ties / "
             f"losses per trial (tie: |Δ| < {TIE_DEG}°) and the two-sided Wilcoxon signed-rank p. `madgwick_tagp`: "
             "Madgwick at its TAGP on the training datasets (BROAD's β grid); `madgwick`: at BROAD's TAGP.", ""]
    for ds, per in results.items():
        index = DatasetIndex.from_dir(by_name[ds])
        names = sorted(per[VQF_TOGGLING])
        groups = [("all", names)] + [(g, [n for n in members if n in per[VQF_TOGGLING]])
                                     for g, members in sorted(index.groups.items())]
        groups = groups[:1] + [(g, m) for g, m in groups[1:] if m and len(m) < len(names)]  # "all" once
        lines += [f"## Left out: {ds} ({len(names)} trials)", "",
                  "| group | trials | " + " | ".join(f"`{r}`" for r in ROWS) + " | learned VQF vs core | "
                  "toggling CF vs core |", "|---" * (len(ROWS) + 4) + "|"]
        for g, members in groups:
            cells = [f"{_mean(per[r], members):.2f}" for r in ROWS]
            lines.append(f"| {g} | {len(members)} | " + " | ".join(cells) + f" | {_vs_core(per, VQF_TOGGLING, members)}"
                         f" | {_vs_core(per, TOGGLING, members)} |")
        lines.append("")
    return "\n".join(lines)


def lodo_json(results: dict) -> dict:
    """dataset -> filter -> trial -> {"total", "heading", "inclination"}: the tables' source numbers."""
    return {ds: {f: {n: {k: r.errors[k] for k in ("total", "heading", "inclination")} for n, r in res.items()}
                 for f, res in per.items()} for ds, per in results.items()}
