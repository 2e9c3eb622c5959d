"""Your sensor, measured: the learned VQF re-learned on one dataset's own recordings.

What a user with their own sensor does (record, import, ``togglecf train --from-pretrained``), measured
on each dataset alone. For each dataset (a directory in BROAD's layout), on its own trials only:
``folds`` test sets by whole trial (``learn.folds.trial_folds``); for each fold and each training size
``n`` of ``sizes`` (the first ``n`` of a seeded shuffle of the fold's training trials, so the sets are
nested; 0 stands for all of them), on those ``n`` recordings only:

* ``vqf_tuned``: the VQF core at its TAGP over τ_acc × τ_mag (the study's ``[baselines.vqf_core]``
  grid) on the ``n`` recordings: what tuning VQF's two time constants on the same data gives;
* ``relearned``: ``togglecf train --from-pretrained`` (``run.pretrained.retune_pretrained``, 9D) from a base
  model that never saw the dataset (``bases``, e.g. from ``base_models``: the pretrained recipe trained on the
  other datasets, e.g. leave-one-dataset-out's ``without_<name>/models``);
* ``guarded``: the same with ``--guard``: the re-learned settings where the guard (``run.pretrained.
  relearning_guard``: re-learned on 2/3 of the ``n`` recordings, checked on the rest, 3 times) finds they beat the
  VQF core by one standard error, else the VQF core (fewer than 3 recordings: always the core);
* ``scratch``: ``togglecf train`` (the default recipe, gain mode ``vqf_9d``) on the ``n`` recordings
  (sizes of ``scratch_sizes`` only: it trains the models too);

the re-learning searches σ_f, the scale of the learned VQF's back-off on the field's change (step 3b of
``filters.vqf_toggling``), as ``togglecf train --from-pretrained`` does by default (``[gains.relearn]``,
``run.config.relearn_search``); ``with_field_change`` gives the training config whose scratch training searches
it too (``FIELD_CHANGE_GRID``), for data of one sensor;

and every held-out trial of the fold is scored with each, beside VQF at its defaults (``vqf_core``,
the grid's point at VQF's default time constants). ``per_sensor_table`` reports, per dataset and
size, the mean total RMSE [°] of each row, each learned row against VQF's defaults and against
``vqf_tuned`` (relative mean, wins / ties / losses, Wilcoxon p), and its worst group against VQF's
defaults (a mean can hide a trade).
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
from togglecf.data.broad import DatasetIndex
from togglecf.filters.vqf_core import VQFCoreSettings
from togglecf.learn.folds import trial_folds
from togglecf.metrics.broad import tagp
from togglecf.parallel.backend import LocalBackend, Task, run_tasks
from togglecf.registry import LEARNED_VQF, VQF_TOGGLING, FilterSpec
from togglecf.report.study_report import TIE_DEG, paired_test
from togglecf.run.config import RELEARN_DEFAULTS, load_config
from togglecf.run.pretrained import GUARD_FOLDS, retune_pretrained, train_pretrained_models
from togglecf.run.scoring import grid_points, score_trial
from togglecf.run.study import load_study_config
from togglecf.run.sweep import evaluate_trials
from togglecf.run.train import run_training
from togglecf.toggling.pretrained import portable_from_model_dir

__all__ = ["PerSensorConfig", "HALF", "ROWS", "LEARNED_ROWS", "FIELD_CHANGE_GRID", "training_subsets", "vqf_grid",
           "base_models", "with_field_change", "per_sensor", "per_sensor_table", "per_sensor_json", "versus",
           "worst_group"]

log = logging.getLogger(__name__)

#: the rows of the tables: VQF at its defaults, VQF tuned on the same recordings, the two learned ones
ROWS = ("vqf_defaults", "vqf_tuned", "relearned", "guarded", "scratch")
#: the learned rows, each compared with VQF's defaults and with ``vqf_tuned``
LEARNED_ROWS = ("relearned", "guarded", "scratch")


@dataclass(frozen=True)
class PerSensorConfig:
    """The protocol's settings: ``folds`` test sets by whole trial per dataset; ``sizes`` the numbers of
    training recordings of the learning curve (0: all of the fold's training trials); ``scratch_sizes``
    those at which the learned VQF is also trained from scratch; ``seed`` of the fold assignment (0:
    round-robin over the sorted names) and of the training subsets' shuffle; ``grid`` the VQF core's
    τ_acc × τ_mag grid [s] (None: the study config's ``[baselines.vqf_core]``)."""

    folds: int = 5
    sizes: tuple = (2, 4, 8, 0)
    scratch_sizes: tuple = (2, 4, 8, 0)
    seed: int = 0
    grid: dict | None = None

    def vqf_grid(self) -> dict:
        grid = self.grid if self.grid is not None else load_study_config().baselines["vqf_core"]
        grid = {k: [float(v) for v in vals] for k, vals in grid.items()}
        defaults = VQFCoreSettings()
        for k in ("tau_acc", "tau_mag"):  # VQF's defaults must be a point of the grid: its own row
            if getattr(defaults, k) not in grid[k]:
                grid[k] = sorted(grid[k] + [getattr(defaults, k)])
        return grid


#: the kept-back check's own split: re-learn (and train) on half of a dataset's recordings, score the other half
HALF = PerSensorConfig(folds=2, sizes=(0,), scratch_sizes=(0,))
#: µT: the σ_f grid of ``with_field_change``, the re-learning's (``RELEARN_DEFAULTS``; 0: off; up to 50 µT, the
#: headroom's back-off grid: a phone's field wants a gentler back-off than BROAD's)
FIELD_CHANGE_GRID = RELEARN_DEFAULTS["field_change_scale"]


def with_field_change(config=None, grid=FIELD_CHANGE_GRID) -> dict:
    """The training config ``config`` (a TOML path, a parsed config or None: the package's) with
    ``field_change_scale`` set to ``grid`` [µT] in ``[gains.vqf]`` and ``[gains.relearn]``: the scratch training
    and the re-learning then search the back-off on the field's change (``VQFGainSearch``)."""
    cfg = load_config(config)
    grid = [float(v) for v in grid]
    for table in ("vqf", "relearn"):
        cfg["gains"][table] = {**cfg["gains"].get(table, {}), "field_change_scale": grid}
    return load_config(cfg)


def training_subsets(train, sizes, seed: int = 0) -> dict:
    """size -> the first ``size`` trials of a seeded shuffle of ``train`` (nested sets; 0 or a size of
    at least ``len(train)``: all of them, under the key 0). Sizes below 2 are refused (training needs two)."""
    order = sorted(train)
    order = [order[i] for i in np.random.default_rng(seed).permutation(len(order))]
    out = {}
    for n in sizes:
        if 0 < n < 2:
            raise ValueError(f"a training size must be at least 2 (or 0 for all), got {n}")
        key = 0 if n == 0 or n >= len(order) else int(n)
        out[key] = order if key == 0 else order[:key]
    return out


def vqf_grid(index: DatasetIndex, names, grid: dict, jobs: int | None = None, store=None) -> dict:
    """The VQF core (9D) at every point of ``grid`` on every trial of ``names``: ``{(tau_acc, tau_mag):
    {trial: errors}}`` (``errors``: BROAD's RMSEs [°]); ``store``: a ``run.sweep.ResultStore``."""
    points = grid_points(grid)
    res = evaluate_trials(index, names, "vqf_core", points, jobs=jobs, store=store)
    return {tuple(p.values()): {n: r[n].errors for n in names} for p, r in zip(points, res)}


def _tagp_on(grid: dict, scored: dict, names) -> dict:
    return tagp(grid, {k: {n: per[n] for n in names} for k, per in scored.items()}).params


def _fold_task(root: Path, name: str, k: int, test: list, subsets: dict, scratch_sizes, base_model, out_dir: Path,
               config, log_level) -> dict:
    """One fold of one dataset (a task): for each training size, re-learn from ``base_model`` and (sizes
    of ``scratch_sizes``) train from scratch on the subset, and score ``test``. Returns ``{size: ({row:
    {trial: errors}} for the learned rows, whether the guard kept the re-learned settings or None)}``."""
    follow_parent_logging(log_level)
    index = DatasetIndex.from_dir(root)
    loaded = {n: index.load(n) for n in test}
    out = {}
    for size, subset in subsets.items():
        t0 = time.perf_counter()
        rows, kept = {}, None
        if base_model is not None:
            where = out_dir / f"fold{k}" / f"n{size or 'all'}"
            res = retune_pretrained(config, data_dir=str(root), trials=subset, out=where / "relearned",
                                    model=base_model, verbose=False, modes=("vqf_9d",), guard_folds=GUARD_FOLDS)
            kept = bool(res["guard"]["vqf_9d"]["passed"])
            spec = FilterSpec(LEARNED_VQF, models=str(res["path"]))
            rows["guarded"] = {n: score_trial(t, spec)[0].errors for n, t in loaded.items()}
            rows["relearned"] = rows["guarded"]  # the guard kept them, or they are the core's anyway
            if res["unguarded_path"] is not None:
                spec = FilterSpec(LEARNED_VQF, models=str(res["unguarded_path"]))
                rows["relearned"] = {n: score_trial(t, spec)[0].errors for n, t in loaded.items()}
        if size in scratch_sizes:
            cfg = load_config(config)
            cfg["gains"]["modes"] = ["vqf_9d"]
            model_dir = out_dir / f"fold{k}" / f"n{size or 'all'}" / "scratch"
            run_training(cfg, data_dir=str(root), trials=subset, out=model_dir, verbose=False)
            spec = FilterSpec(VQF_TOGGLING, models=str(model_dir))
            rows["scratch"] = {n: score_trial(t, spec)[0].errors for n, t in loaded.items()}
        out[size] = (rows, kept)
        log.info(f"  {name} fold {k}: {len(subset)} training recordings, {len(test)} scored in "
                 f"{time.perf_counter() - t0:.0f} s")
    return out


def _base_portable(base, out: Path) -> Path | None:
    """A portable model file for ``base``: the file itself, or one written from a model directory."""
    if base is None:
        return None
    base = Path(base)
    if base.is_file():
        return base
    return portable_from_model_dir(base, out, {"recipe": f"the models of {base}, as the base of the re-learning"})


def base_models(dirs, base_from, out) -> dict:
    """dataset name -> a model directory of the pretrained recipe that never saw it: ``base_from/without_<name>/
    models`` when it holds gains, else trained here on the other datasets (none when a dataset is alone)."""
    bases = {}
    for d in dirs:
        d = Path(d)
        given = Path(base_from) / f"without_{d.name}" / "models"
        if (given / "gains.json").is_file():
            bases[d.name] = given
            continue
        others = [Path(o) for o in dirs if Path(o) != d]
        if not others:
            log.warning(f"{d.name}: no other dataset to train a base on: no re-learned row")
            continue
        log.info(f"per sensor: {d.name}: no {given}: training the base on {', '.join(o.name for o in others)}")
        bases[d.name] = train_pretrained_models(others, Path(out) / "base" / f"without_{d.name}")
    return bases


def per_sensor(dirs, out_dir, bases: dict | None = None, settings: PerSensorConfig | None = None, config=None,
               jobs: int | None = None, store=None, backend=None) -> dict:
    """The protocol of the module docstring on each directory of ``dirs``. ``bases``: dataset
    name -> the base of the re-learning (a portable file or a ``togglecf train`` directory that never
    saw that dataset); a dataset without one has no ``relearned`` and ``guarded`` rows. Returns ``{dataset:
    {"folds": [[trial, ...], ...], "grid": {...}, "sizes": {size: {row: {trial: errors}}}, "tuned": {size:
    [params per fold]}, "guard_kept": {size: [bool per fold]}}}``."""
    settings = settings or PerSensorConfig()
    bases = bases or {}
    out_dir = Path(out_dir)
    grid = settings.vqf_grid()
    defaults = (VQFCoreSettings().tau_acc, VQFCoreSettings().tau_mag)
    plans, tasks = {}, []
    for d in map(Path, dirs):
        index = DatasetIndex.from_dir(d)
        names = index.select(None)
        folds = trial_folds(names, settings.folds, settings.seed)
        t0 = time.perf_counter()
        scored = vqf_grid(index, names, grid, jobs, store)
        log.info(f"per sensor: {d.name}: VQF's grid ({len(scored)} points x {len(names)} trials) in "
                 f"{time.perf_counter() - t0:.0f} s")
        base = _base_portable(bases.get(d.name), out_dir / d.name / "base_learned_vqf.npz")
        plan = {"folds": folds, "grid": grid, "sizes": {}, "tuned": {}, "guard_kept": {}}
        for k, test in enumerate(folds):
            train = [n for n in names if n not in test]
            subsets = training_subsets(train, settings.sizes, settings.seed + k)
            scratch = tuple(training_subsets(train, settings.scratch_sizes, settings.seed + k)) if settings.scratch_sizes else ()
            for size, subset in subsets.items():
                params = _tagp_on(grid, scored, subset)
                key = tuple(params.values())
                rows = plan["sizes"].setdefault(size, {r: {} for r in ROWS[:2]})
                rows["vqf_defaults"].update({n: scored[defaults][n] for n in test})
                rows["vqf_tuned"].update({n: scored[key][n] for n in test})
                plan["tuned"].setdefault(size, []).append(params)
            tasks.append(Task((d.name, k), _fold_task, (d, d.name, k, test, subsets, scratch,
                                                       base, out_dir / d.name, config, configured_level())))
        plans[d.name] = plan
    # forkserver: a task trains XGBoost, whose OpenMP runtime does not survive a fork (LocalBackend)
    backend = backend or LocalBackend(min(jobs or os.cpu_count() or 1, max(1, len(tasks))), start_method="forkserver")
    done = run_tasks(backend, tasks, desc="per sensor", unit="fold")
    for (name, k), sizes in sorted(done.items()):
        for size, (rows, kept) in sizes.items():
            for row, per in rows.items():
                plans[name]["sizes"][size].setdefault(row, {}).update(per)
            if kept is not None:
                plans[name]["guard_kept"].setdefault(size, []).append(kept)
    return plans


def _mean(per: dict, names, metric: str = "total") -> float:
    return float(np.mean([per[n][metric] for n in names])) if names else float("nan")


def versus(per: dict, ref: dict, names) -> str:
    """Relative change of the mean total RMSE, wins / ties / losses and Wilcoxon p of ``per`` against ``ref``."""
    if len(names) < 2:
        return ""
    t = paired_test([per[n]["total"] - ref[n]["total"] for n in names])
    rel = 100.0 * (_mean(per, names) / _mean(ref, names) - 1.0)
    return f"{rel:+.1f} % · {t['wins']}/{t['ties']}/{t['losses']} · p {t['p']:.2g}"


def worst_group(per: dict, ref: dict, groups: dict) -> str:
    """The group (of at least two trials) where ``per`` is worst against ``ref``, relative mean change."""
    worst = None
    for g, members in groups.items():
        m = [n for n in members if n in per]
        if len(m) < 2:
            continue
        rel = 100.0 * (_mean(per, m) / _mean(ref, m) - 1.0)
        if worst is None or rel > worst[1]:
            worst = (g, rel)
    return "" if worst is None else f"{worst[0]} {worst[1]:+.1f} %"


def per_sensor_table(results: dict, dirs, command: str) -> str:
    """Markdown: per dataset, one line per training size with the mean total RMSE [°] of ``ROWS`` over
    the held-out trials, each learned row against VQF's defaults and against ``vqf_tuned``, and its
    worst group against VQF's defaults; last, ``vqf_tuned``'s worst group against VQF's defaults."""
    by_name = {Path(d).name: Path(d) for d in dirs}
    lines = [generated_line(command), "",
             "Each dataset alone: folds by whole trial within it; each row learned or tuned on *n* of the fold's "
             "training recordings only (*all*: every one), every held-out trial scored. Mean total RMSE [°] (BROAD's "
             "metric). `vqf_defaults`: VQF at its defaults; `vqf_tuned`: VQF with τ_acc × τ_mag at their TAGP on the "
             "same *n* recordings; `relearned`: `togglecf train --from-pretrained` (the config's `[gains.relearn]` "
             "search) from a model that never saw the dataset; `guarded`: the same with `--guard`, the re-learned "
             "settings where the guard (re-learned on 2/3 of the *n* recordings, checked on the rest, 3 times) finds "
             "they beat VQF's core by one standard error, else the core (*guard kept*: in how many folds; below 3 "
             "recordings never); `scratch`: `togglecf train` on the *n* recordings (its `[gains.vqf]` search). "
             "*vs* columns: relative change of the mean, "
             f"wins / ties / losses per trial (tie: |Δ| < {TIE_DEG}°), two-sided Wilcoxon p; *worst group*: the group "
             "(≥ 2 trials) where the learned row does worst against VQF's defaults; *tuned worst group*: the same for "
             "`vqf_tuned` (a group the learned rows share it with follows from VQF's two time constants).", ""]
    for ds, plan in results.items():
        index = DatasetIndex.from_dir(by_name[ds])
        lines += [f"## {ds} ({sum(len(f) for f in plan['folds'])} trials, {len(plan['folds'])} folds)", "",
                  "| n | " + " | ".join(f"`{r}`" for r in ROWS) + " | guard kept | "
                  + " | ".join(f"{r} {c}" for r in LEARNED_ROWS for c in ("vs defaults", "vs tuned", "worst group"))
                  + " | tuned worst group |", "|---" * (len(ROWS) + 3 + 3 * len(LEARNED_ROWS)) + "|"]
        for size in sorted(plan["sizes"], key=lambda s: (s == 0, s)):
            rows = plan["sizes"][size]
            names = sorted(rows["vqf_defaults"])
            cells = [f"{_mean(rows[r], names):.2f}" if len(rows.get(r, {})) == len(names) else "" for r in ROWS]
            cmp = []
            for r in LEARNED_ROWS:
                if len(rows.get(r, {})) != len(names):
                    cmp += ["", "", ""]
                    continue
                cmp += [versus(rows[r], rows["vqf_defaults"], names), versus(rows[r], rows["vqf_tuned"], names),
                        worst_group(rows[r], rows["vqf_defaults"], index.groups)]
            tuned = worst_group(rows["vqf_tuned"], rows["vqf_defaults"], index.groups) if cells[1] else ""
            kept = plan.get("guard_kept", {}).get(size, [])
            guard = f"{sum(kept)}/{len(kept)}" if kept else ""
            lines.append(f"| {size or 'all'} | " + " | ".join(cells + [guard] + cmp + [tuned]) + " |")
        lines.append("")
    return "\n".join(lines)


def per_sensor_json(results: dict) -> dict:
    """The tables' source numbers: dataset -> folds, the tuned pairs, the guard's decision per fold and
    size -> row -> trial -> {"total", "heading", "inclination"}."""
    keep = ("total", "heading", "inclination")
    return {ds: {"folds": plan["folds"], "tuned": {str(s): p for s, p in plan["tuned"].items()},
                 "guard_kept": {str(s): k for s, k in plan.get("guard_kept", {}).items()},
                 "sizes": {str(s): {r: {n: {k: e[k] for k in keep} for n, e in per.items()}
                                    for r, per in rows.items()} for s, rows in plan["sizes"].items()}}
            for ds, plan in results.items()}
