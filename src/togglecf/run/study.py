"""The held-out study: the toggling CF against the classic filters and VQF, trial by trial.

Protocol (no number here is measured on data its models or parameters were fitted on):

* trials are split into ``folds`` groups by whole trial (round-robin over the sorted names, so
  every fold mixes BROAD's groups);
* per fold, on the *training* trials only: the models are trained (``togglecf train`` with the
  study's config, no CV), the toggling gains are learned (``gains.learn_gains`` on the models'
  predictions for those trials), and each baseline takes its TAGP over its grid;
* the fold's *test* trials are then filtered: the toggling CF with its models compiled into
  the loop, each baseline at its training-fold TAGP, VQF at its defaults (not tuned).

This module holds the protocol: the config, the plan (``plan_study``: trials, folds, baseline
grids), the fold task and ``finish`` (the report). What a fold scores, the learned, baseline and
ablation rows, is ``run.study_rows``.
"""
from __future__ import annotations

import logging
import os
import time
import tomllib
from dataclasses import dataclass, field
from pathlib import Path

from togglecf.core.config import config_path
from togglecf.core.log import configured_level, follow_parent_logging
from togglecf.core.provenance import source_revision
from togglecf.data.broad import open_index
from togglecf.learn.folds import trial_folds
from togglecf.parallel.backend import LocalBackend, Task, data_location, run_tasks
from togglecf.registry import VQF_TOGGLING, FilterSpec
from togglecf.report.study_report import write_report
from togglecf.run.config import GAIN_KEYS, load_config
from togglecf.run.scoring import grid_points, parse_grid, run_filter
from togglecf.run.study_rows import (LEARNED_ROWS, PLOTTED_BASELINES, FoldData, ablation_rows, baseline_rows,
                                     chosen_params, default_rows, errors_series, learn_vqf_variant,
                                     oracle_predictions, rest_bias_grid, score_learned, tagp_on, vqf_variant_errors)
from togglecf.run.sweep import evaluate_trials
from togglecf.run.train import run_training
from togglecf.toggling.gains import GainSearch, VQFGainSearch, describe_gains, mode_name

__all__ = ["StudyConfig", "StudyPlan", "load_study_config", "plan_study", "run_study", "tagp_on", "oracle_predictions",
           "learn_vqf_variant", "vqf_variant_errors"]

DEFAULT_STUDY_CONFIG = config_path("study.toml")
ABLATIONS = ("toggling_only", "noise_only", "6d", "ransac_off", "vqf_taus_only", "vqf_oracle", "madgwick_rest_bias")


@dataclass
class StudyConfig:
    """Settings of ``run_study`` (see ``togglecf/configs/study.toml``).

    Attributes:
        folds: number of trial folds.
        inner_folds: CV folds inside each training set; their out-of-fold predictions are what
            the gains are learned on (as ``togglecf train`` does).
        train_config: path of the ``togglecf train`` TOML used in every fold.
        baselines: filter name -> parameter grid (name -> values), 9D.
        baselines_6d: the same for the 6D comparison.
        gains: the gain search of the ablations (the main gains are learned by ``togglecf train``
            with the ``[gains]`` of ``train_config``; this is the same search, read from there).
        vqf_gains: the VQF core's learned-time-constant search (``[gains.vqf]`` of ``train_config``).
        ablations: which of ``ABLATIONS`` to run.
        jobs: worker processes.
        fold_seed: 0 for the standard fold assignment, another value for a shuffled one
            (``learn.folds.trial_folds``; the spread of the results over assignments).
    """

    folds: int = 5
    inner_folds: int = 3
    train_config: str = ""
    baselines: dict = field(default_factory=dict)
    baselines_6d: dict = field(default_factory=dict)
    gains: GainSearch = field(default_factory=GainSearch)
    vqf_gains: VQFGainSearch = field(default_factory=VQFGainSearch)
    ablations: tuple = ABLATIONS
    jobs: int = 0
    fold_seed: int = 0


def load_study_config(path=None) -> StudyConfig:
    path = Path(path or DEFAULT_STUDY_CONFIG)
    with open(path, "rb") as f:
        raw = tomllib.load(f)
    st = raw.get("study", {})
    unknown = set(st) - {"folds", "inner_folds", "train_config", "ablations", "jobs", "fold_seed"}
    if unknown:
        raise ValueError(f"{path}: [study] unknown key(s) {sorted(unknown)}")
    train_config = st.get("train_config", "default.toml")
    if not Path(train_config).is_absolute():
        train_config = str((path.parent / train_config).resolve())

    def grids(section):
        return {name: parse_grid([f"{k}={v}" if isinstance(v, str) else f"{k}={','.join(map(str, v))}"
                                  for k, v in g.items()]) for name, g in raw.get(section, {}).items()}

    g = load_config(train_config)["gains"]
    search = GainSearch.from_dict({k: v for k, v in g.items() if k not in GAIN_KEYS})
    vqf_search = VQFGainSearch.from_dict(g.get("vqf", {}))
    ablations = tuple(st.get("ablations", ABLATIONS))
    bad = set(ablations) - set(ABLATIONS)
    if bad:
        raise ValueError(f"{path}: unknown ablation(s) {sorted(bad)}; known: {list(ABLATIONS)}")
    return StudyConfig(folds=int(st.get("folds", 5)), inner_folds=int(st.get("inner_folds", 3)), train_config=train_config, baselines=grids("baselines"),
                       baselines_6d=grids("baselines_6d"), gains=search, vqf_gains=vqf_search, ablations=ablations,
                       jobs=int(st.get("jobs", 0)), fold_seed=int(st.get("fold_seed", 0)))


log = logging.getLogger(__name__)


def _baseline_grids(index, names, grids, use_mag, jobs, store=None):
    """filter -> (list of params, list over params of trial -> TrialResult); ``store``: a
    ``ResultStore`` that keeps them (``run_study``)."""
    out = {}
    for filt, grid in grids.items():
        keys = grid_points(grid)
        t0 = time.perf_counter()
        res = evaluate_trials(index, names, filt, keys, use_mag=use_mag, jobs=jobs, store=store)
        log.info(f"  {filt} {'9D' if use_mag else '6D'}: {len(keys)} grid points x {len(names)} trials "
             f"in {time.perf_counter() - t0:.1f} s")
        out[filt] = (keys, res)
    return out


@dataclass(frozen=True)
class _FoldJob:
    """What a fold task needs (picklable: paths and settings, no arrays; the fold loads its trials from
    ``root`` where it runs)."""

    cfg: StudyConfig
    train_cfg: dict
    root: object  # ``data_location`` of the index
    names: tuple
    out: Path
    jobs: int
    log_level: int | None  # the parent's ``configured_level``: a worker logs the fold's progress as it does


def _load_trials(root, names) -> dict:
    """name -> Trial for ``names``, loaded from ``root`` (a ``data_location``) in this process."""
    index = open_index(list(root) if isinstance(root, tuple) else root)
    return {n: index.load(n) for n in names}


def run_study(config: StudyConfig | None = None, data_dir=None, out_dir="reports/study", trials=None, backend=None,
              store=None) -> dict:
    """Run the whole study and write its report; returns the result tables (see ``report``).

    ``backend`` (``togglecf.parallel``) runs the folds as tasks (default: a local process pool on
    ``jobs`` cores; with Dask the data and ``out_dir`` must be on a filesystem the workers share);
    ``store`` (a ``run.sweep.ResultStore``) keeps the baseline grids' results, so that a later study
    on the same trials computes none of them again. ``plan_study`` runs it in parts (``make run``
    runs its folds on one pool with other steps' tasks)."""
    plan = plan_study(config, data_dir, out_dir, trials)
    plan.evaluate_grids(store)
    # forkserver: a fold trains XGBoost, whose OpenMP runtime does not survive a fork (LocalBackend)
    backend = backend or LocalBackend(min(plan.jobs, len(plan.folds)), start_method="forkserver")
    t0 = time.perf_counter()
    done = run_tasks(backend, plan.tasks(), desc="study folds", unit="fold")
    return plan.finish(done, folds_s=time.perf_counter() - t0)


@dataclass
class StudyPlan:
    """A study whose folds are ready to run (``plan_study``): ``evaluate_grids`` runs the baseline grids,
    ``tasks()`` are the folds (``parallel.Task``, keys ``(label, k)``), ``finish(done)`` assembles their
    results (key -> value, as ``parallel.run_tasks`` returns them) with the grids and writes the report.
    The grids and the folds are independent."""

    cfg: StudyConfig
    job: _FoldJob
    names: list
    folds: list
    loaded: dict
    index: object
    out: Path
    timing: dict
    t_start: float
    label: str = "study"
    grids: dict = field(default_factory=dict)  # "9d", "6d", "rest_bias" -> filter -> (params, results per point)

    @property
    def jobs(self) -> int:
        return self.job.jobs

    def tasks(self) -> list:
        return [Task((self.label, k), _run_fold, (self.job, k, test)) for k, test in enumerate(self.folds)]

    def evaluate_grids(self, store=None, jobs: int | None = None) -> None:
        """Every baseline's grid on every trial (each fold takes its TAGP on its training trials from them),
        on ``jobs`` processes (default the study's; 1: in this process); ``store``: see ``run_study``."""
        cfg, index, names = self.cfg, self.index, self.names
        jobs = jobs or self.jobs
        log.info("baselines: evaluating grids on all trials (each fold picks its TAGP on its training trials)")
        t0 = time.perf_counter()
        self.grids = {"9d": _baseline_grids(index, names, cfg.baselines, True, jobs, store),
                      "6d": (_baseline_grids(index, names, cfg.baselines_6d, False, jobs, store)
                             if "6d" in cfg.ablations else {}),
                      "rest_bias": {}}
        if "madgwick_rest_bias" in cfg.ablations and "madgwick" in cfg.baselines:
            self.grids["rest_bias"]["madgwick_rest_bias"] = rest_bias_grid(cfg.baselines["madgwick"], self.loaded,
                                                                           names)
        self.timing["baseline_grids_s"] = time.perf_counter() - t0

    def finish(self, done: dict, folds_s: float | None = None) -> dict:
        """The report from the folds' results ``done``; ``folds_s``: their wall time, when they ran alone."""
        if folds_s is not None:
            self.timing["folds_s"] = folds_s
        loaded, names = self.loaded, self.names
        rows, fold_info = [], []
        series = {n: {} for n in names}  # per-sample total error [deg] for the plots
        timelines = {}
        for k, test in enumerate(self.folds):
            fold = done[(self.label, k)]
            info, train = fold["info"], fold["info"]["train"]
            rows += fold["rows"] + baseline_rows(self.grids["9d"], train, test, k, info)
            for n in test:
                series[n].update(fold["series"][n])
                series[n].update({f: errors_series(run_filter(loaded[n], FilterSpec(f, p))[0].quat, loaded[n])
                                  for f, p in chosen_params(info, PLOTTED_BASELINES)})
            timelines.update(fold["timelines"])
            rows += (baseline_rows(self.grids["rest_bias"], train, test, k, {})
                     + baseline_rows(self.grids["6d"], train, test, k, {}, "_6d"))
            fold_info.append(info)
        rows += default_rows(loaded, names, "6d" in self.cfg.ablations, series)

        self.timing["total_s"] = time.perf_counter() - self.t_start
        result = {"rows": rows, "folds": fold_info, "timing": self.timing, "trials": names,
                  "missing": self.index.missing, "fold_seed": self.cfg.fold_seed, "groups": self.index.groups,
                  "code": source_revision()}
        write_report(self.out, result, series, timelines, loaded)
        log.info(f"study done in {self.timing['total_s']:.0f} s; report in {self.out}/")
        return result


def plan_study(config: StudyConfig | None = None, data_dir=None, out_dir="reports/study", trials=None) -> StudyPlan:
    """The study up to its folds and grids (``run_study``'s arguments): the trials loaded, the folds made."""
    cfg = config or load_study_config()
    jobs = cfg.jobs or os.cpu_count() or 1
    t_start = time.perf_counter()
    index = open_index(data_dir or load_config(cfg.train_config)["run"]["data"] or None)  # --data > [run] data
    names = index.select(trials)
    log.info(index.summary())
    folds = trial_folds(names, cfg.folds, cfg.fold_seed)
    job = _FoldJob(cfg, _fold_train_config(cfg), data_location(index), tuple(names), Path(out_dir), jobs,
                   configured_level())
    loaded = _load_trials(job.root, names)
    return StudyPlan(cfg, job, names, folds, loaded, index, Path(out_dir), {}, t_start)


def _fold_train_config(cfg: StudyConfig) -> dict:
    """The ``togglecf train`` config of every fold: the gains of every mode the rows need, learned
    on the inner CV's out-of-fold predictions."""
    train_cfg = load_config(cfg.train_config)
    six_d = "6d" in cfg.ablations
    train_cfg["gains"].update(learn=True, modes=(["9d", "6d", "vqf_9d", "vqf_6d"] if six_d else ["9d", "vqf_9d"]))
    train_cfg["run"]["cv_folds"] = cfg.inner_folds
    return train_cfg


def _run_fold(job: _FoldJob, k: int, test: list) -> dict:
    """Fold ``k`` (a task): train on every other trial, learn the gains, score the learned rows and
    the ablations on ``test``. Returns its rows, error series, timelines and ``info``."""
    follow_parent_logging(job.log_level)
    loaded = _load_trials(job.root, job.names)
    train = [n for n in job.names if n not in test]
    log.info(f"fold {k + 1}: train on {len(train)} trials, test on {', '.join(test)}")
    # inner CV, models, then the gains on the CV's out-of-fold predictions: used as trained (in memory), the
    # directory written for the report's readers and the later steps (run.transfer reads each fold's models)
    res = run_training(job.train_cfg, data_dir=job.root, trials=",".join(train), out=_fold_dir(job, k, "models"),
                       cv=True, verbose=False)
    trained = res["trained"]
    models, gains9 = trained.models, trained.gains["9d"].settings
    info = {"fold": k, "train": train, "test": test, **_fold_gains_info(res)}
    log.info(f"  fold {k + 1}: models {info['train_s']:.0f} s, gains {info['gains_s']:.0f} s: {info['gains']}; "
             f"learned VQF: {info['vqf_gains']}")
    out = {"rows": [], "series": {n: {} for n in test}, "timelines": {}, "info": info}
    for spec in LEARNED_ROWS:
        if spec.needs is None or spec.needs in job.cfg.ablations:
            score_learned(spec, [loaded[n] for n in test], trained, k, out)
    # test trials: the fold's final models; training trials: the inner CV's out-of-fold predictions
    preds = {n: models.predict_samples(loaded[n].gyr, loaded[n].acc, loaded[n].mag, loaded[n].fs) for n in test}
    preds.update(res["oof_predictions"])
    t0 = time.perf_counter()
    fold = FoldData(k, train, test, loaded, preds, models, gains9, info, trained.gains,
                    _fold_dir(job, k, "models_ransac_off"))
    out["rows"] += ablation_rows(job, fold)
    info["ablations_s"] = time.perf_counter() - t0
    return out


def _fold_dir(job: _FoldJob, k: int, name: str) -> Path:
    """Where fold ``k`` writes its model directory ``name`` (``models``, ``models_ransac_off``)."""
    return job.out / "folds" / f"fold{k}" / name


def _fold_gains_info(res: dict) -> dict:
    """Timing and learned settings of a fold's training (``info`` of the fold in ``results.json``)."""
    gains = res["trained"].gains
    gains9, hist = gains["9d"]
    t = res["timing"]
    return {"train_s": t["final_fit_s"] + t["dataset_s"] + t.get("cv_s", 0.0), "gains_s": t.get("gains_s", 0.0),
            "gains": {"tau_acc": gains9.tau_acc, "tau_mag": gains9.tau_mag, "output_tau": gains9.output_tau,
                      "bias_tau": gains9.bias_tau, "mag_disturbance_scale": gains9.mag_disturbance_scale,
                      "noise_weight_acc": gains9.noise_weight_acc, "noise_weight_mag": gains9.noise_weight_mag,
                      "confidence_floor": gains9.confidence_floor,
                      "mag_rate_limit": gains9.mag_rate_limit, "train_objective": float(hist[-1][2])},
            "vqf_gains": describe_gains(gains[mode_name(VQF_TOGGLING, True)].settings)}


