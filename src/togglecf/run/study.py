"""The held-out study: the toggling CF against the classic filters and VQF, trial by trial.

Protocol (no number here is measured on data its models or parameters were fitted on):

* trials are split into ``folds`` groups by whole trial (round-robin over the sorted names, so
  every fold mixes BROAD's groups);
* per fold, on the *training* trials only: the models are trained (``togglecf train`` with the
  study's config, no CV), the toggling gains are learned (``gains.learn_gains`` on the models'
  predictions for those trials), and each baseline takes its TAGP over its grid;
* the fold's *test* trials are then filtered: the toggling CF with its models compiled into
  the loop, each baseline at its training-fold TAGP, VQF at its defaults (not tuned).

Ablations (same folds, same models; predictions fed to ``TogglingFilter``):
``toggling_only`` (η̂ = 0), ``noise_only`` (one gain for all states, no rest bias), ``6d``
(no magnetometer, gains learned in 6D, compared with 6D baselines at their 6D TAGP) and
``ransac_off`` (models retrained without RANSAC cleaning).
"""
from __future__ import annotations

import json
import logging
import os
import time
import tomllib
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from togglecf.core.config import config_path
from togglecf.core.log import configured_level, follow_parent_logging
from togglecf.core.provenance import source_revision
from togglecf.data.broad import open_index
from togglecf.filters.prediction import PredictionLayout
from togglecf.filters.toggling import TogglingFilter
from togglecf.filters.vqf_toggling import VQFTogglingFilter
from togglecf.learn.folds import trial_folds
from togglecf.learn.labels import LabelSettings, make_targets
from togglecf.metrics.broad import error_angles_rad, error_quaternion, remove_heading_offset, tagp, trial_errors
from togglecf.parallel.backend import LocalBackend, Task, data_location, run_tasks
from togglecf.registry import TOGGLING, VQF_TOGGLING, FilterSpec
from togglecf.report.study_report import write_report
from togglecf.run.config import GAIN_KEYS, load_config
from togglecf.run.scoring import grid_points, parse_grid, run_built, run_filter, score_trial
from togglecf.run.sweep import evaluate_trials
from togglecf.run.train import TrainedModels, run_training
from togglecf.toggling.gains import GainSearch, VQFGainSearch, describe_gains, learn_gains, mode_name
from togglecf.toggling.load import IN_LOOP

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


def without_initial_rest_bias(trial, min_rest_s: float = 1.0):
    """``trial`` with the gyro bias of its initial rest removed: the mean gyro reading before the
    first ``movement`` sample (BROAD's annotation), when that rest lasts at least ``min_rest_s``
    (else unchanged). The bracket for Madgwick raised on BROAD's tracker
    (https://github.com/dlaidig/broad/issues/2): what a rest-bias calibration at start-up gives a
    filter that does not estimate the bias itself."""
    moving = np.flatnonzero(trial.movement)
    n_rest = int(moving[0]) if moving.size else trial.n_samples
    if n_rest < min_rest_s * trial.fs:
        return trial
    rest = trial.gyr[:n_rest]
    bias = np.nanmean(rest[np.all(np.isfinite(rest), axis=1)], axis=0)
    return replace(trial, gyr=trial.gyr - bias)


def oracle_predictions(trial, label_settings, class_names) -> np.ndarray:
    """Per-sample predictions ``(N, S + 6)`` from the *true* motion state (the labels made from
    the optical reference): one-hot probabilities where the label is valid, NaN elsewhere (the
    filter then uses its fallback: the learned VQF filter its core, the toggling CF its cautious gains);
    zero predicted noise."""
    targets = make_targets(trial, label_settings)
    if tuple(targets.state_names) != tuple(class_names):
        raise ValueError(f"label states {targets.state_names} differ from the model's classes {class_names}")
    layout = PredictionLayout.of(len(class_names))
    pred = np.zeros((trial.n_samples, layout.size))
    valid = targets.valid & (targets.state >= 0)
    pred[np.flatnonzero(valid), targets.state[valid]] = 1.0
    pred[~valid, layout.probabilities] = np.nan
    return pred


def _errors_series(q, t, six_d=False):
    if six_d:
        q = remove_heading_offset(q, t.opt_quat, t.movement)
    return np.degrees(error_angles_rad(error_quaternion(q, t.opt_quat))["total"])


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


def tagp_on(train_names, keys, res):
    """BROAD's TAGP of a grid over the named trials only (a fold's training trials): ``keys`` the grid's
    parameter dicts, ``res[i]`` trial -> ``TrialResult`` of ``keys[i]``. Returns (index into ``keys``, its
    parameters, their mean total RMSE [deg] over ``train_names``)."""
    grid = {k: list(dict.fromkeys(p[k] for p in keys)) for k in keys[0]}
    t = tagp(grid, {tuple(p.values()): {n: r[n].errors for n in train_names} for p, r in zip(keys, res)})
    i = keys.index(t.params)
    return i, keys[i], float(np.nanmin(t.mean_total))


def _vqf(trial, use_mag=True):
    from vqf import VQF

    v = VQF(1.0 / trial.fs)
    t0 = time.perf_counter()
    out = v.updateBatch(np.ascontiguousarray(trial.gyr), np.ascontiguousarray(trial.acc),
                        np.ascontiguousarray(trial.mag) if use_mag else None)
    us = 1e6 * (time.perf_counter() - t0) / trial.n_samples
    return out["quat9D" if use_mag else "quat6D"], us


def _row(trial: str, label: str, fold: int, errors: dict, us_per_sample=None, params=None) -> dict:
    """One row of the study's tables (``per_trial.csv``): trial, filter label, fold (-1: no training),
    µs per sample when measured, the parameters of a tuned baseline, BROAD's errors [deg]."""
    row = {"trial": trial, "filter": label, "fold": fold}
    if us_per_sample is not None:
        row["us_per_sample"] = us_per_sample
    if params is not None:
        row["params"] = json.dumps(params)
    return row | errors


@dataclass(frozen=True)
class LearnedRow:
    """A learned filter scored on each fold's test trials with the fold's models in the loop:
    ``label`` in the tables, the registry filter, 9D/6D, whether its error series is plotted, and
    the ablation that must be on for the row to run (``None``: always)."""

    label: str
    filter: str
    use_mag: bool = True
    plotted: bool = False
    needs: str | None = None


#: the learned rows of every fold, in table order (the toggling CF's timeline is plotted too)
LEARNED_ROWS = (LearnedRow("toggling", TOGGLING, plotted=True), LearnedRow("vqf_toggling", VQF_TOGGLING, plotted=True),
                LearnedRow("vqf_toggling_6d", VQF_TOGGLING, use_mag=False, needs="6d"))
#: baselines whose error series the plots show
PLOTTED_BASELINES = ("madgwick", "cf")


@dataclass(frozen=True)
class _FoldJob:
    """What a fold task needs (picklable: paths and settings, no arrays)."""

    cfg: StudyConfig
    train_cfg: dict
    root: object  # ``data_location`` of the index
    names: tuple
    out: Path
    jobs: int
    log_level: int | None  # the parent's ``configured_level``: a worker logs the fold's progress as it does


#: trials loaded by this process: (root, name) -> Trial (a worker loads them once for all its folds)
_LOADED: dict = {}


def _trials(root, names) -> dict:
    """name -> Trial, from this process's ``_LOADED`` when there, else loaded from ``root`` here."""
    key = str(root)
    missing = [n for n in names if (key, n) not in _LOADED]
    if missing:
        index = open_index(list(root) if isinstance(root, tuple) else root)
        for n in missing:
            _LOADED[(key, n)] = index.load(n)
    return {n: _LOADED[(key, n)] for n in names}


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
            self.grids["rest_bias"]["madgwick_rest_bias"] = _rest_bias_grid(cfg.baselines["madgwick"], self.loaded,
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
            rows += fold["rows"] + _baseline_rows(self.grids["9d"], train, test, k, info)
            for n in test:
                series[n].update(fold["series"][n])
                series[n].update({f: _errors_series(run_filter(loaded[n], FilterSpec(f, p))[0].quat, loaded[n])
                                  for f, p in _chosen(info, PLOTTED_BASELINES)})
            timelines.update(fold["timelines"])
            rows += (_baseline_rows(self.grids["rest_bias"], train, test, k, {})
                     + _baseline_rows(self.grids["6d"], train, test, k, {}, "_6d"))
            fold_info.append(info)
        rows += _default_rows(loaded, names, "6d" in self.cfg.ablations, series)

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
    loaded = _trials(job.root, names)
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
    loaded = _trials(job.root, job.names)
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
            _score_learned(spec, [loaded[n] for n in test], trained, k, out)
    # test trials: the fold's final models; training trials: the inner CV's out-of-fold predictions
    preds = {n: models.predict_samples(loaded[n].gyr, loaded[n].acc, loaded[n].mag, loaded[n].fs) for n in test}
    preds.update(res["oof_predictions"])
    t0 = time.perf_counter()
    out["rows"] += _ablations(job, _Fold(k, train, test, loaded, preds, models, gains9, info, trained.gains))
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
                      "confidence_floor": gains9.confidence_floor, "train_objective": float(hist[-1][2])},
            "vqf_gains": describe_gains(gains[mode_name(VQF_TOGGLING, True)].settings)}


def _score_learned(spec: LearnedRow, trials, trained: TrainedModels, k: int, out: dict) -> None:
    """The rows of ``spec`` on a fold's test ``trials`` (the fold's models, in memory, compiled into the
    loop with the learned settings of the row's mode), into ``out``."""
    settings = trained.gains[mode_name(spec.filter, spec.use_mag)].settings
    class_names = trained.models.class_names

    def build(fs):
        return IN_LOOP[spec.filter](fs, settings, models=trained.models, use_mag=spec.use_mag)
    for t in trials:
        o, us = run_built(t, build, spec.use_mag)
        out["rows"].append(_row(t.name, spec.label, k, trial_errors(o.quat, t.opt_quat, t.movement,
                                                                     six_d=not spec.use_mag), us))
        if not spec.plotted:
            continue
        out["series"][t.name][spec.label] = _errors_series(o.quat, t)
        if spec.filter == TOGGLING:
            out["timelines"][t.name] = {"alpha_acc": o.diagnostics["alpha_acc"],
                                        "p": np.column_stack([o.diagnostics[f"p_{s}"] for s in class_names]),
                                        "states": class_names}


def _baseline_rows(grids: dict, train, test, k: int, info: dict, suffix: str = "") -> list:
    """Each grid's TAGP on the fold's training trials, scored on its test trials (rows ``filter + suffix``);
    the chosen parameters go into ``info["baseline_tagp"]`` (9D only)."""
    rows = []
    for filt, (keys, res) in grids.items():
        i, params, train_err = tagp_on(train, keys, res)
        if not suffix:
            info.setdefault("baseline_tagp", {})[filt] = {"params": params, "train_mean_total": train_err}
        rows += [_row(n, filt + suffix, k, res[i][n].errors, res[i][n].us_per_sample, params) for n in test]
    return rows


def _chosen(info: dict, filters) -> list:
    """(filter, parameters) of the fold's TAGP of each of ``filters`` that has a grid."""
    return [(f, info["baseline_tagp"][f]["params"]) for f in filters if f in info.get("baseline_tagp", {})]


def _rest_bias_grid(grid: dict, loaded: dict, names) -> tuple:
    """The bracket of BROAD's tracker (``without_initial_rest_bias``): Madgwick's grid on the trials with their initial-rest gyro bias removed,
    as ``(params list, [trial -> TrialResult] per point)``."""
    keys = grid_points(grid)
    corrected = {n: without_initial_rest_bias(loaded[n]) for n in names}
    res = [{n: score_trial(corrected[n], FilterSpec("madgwick", p))[0] for n in names} for p in keys]
    log.info(f"  madgwick with the initial-rest gyro bias removed: {len(keys)} grid points x {len(names)} trials")
    return keys, res


def _default_rows(loaded: dict, names, six_d: bool, series: dict) -> list:
    """The filters at their defaults, on every trial (fold -1): the VQF core (ours, from the paper), the
    learned filter without learning, and VQF (the external state of the art) when installed."""
    rows = []
    for n in names:
        for use_mag in (True, False) if six_d else (True,):
            r, _ = score_trial(loaded[n], FilterSpec("vqf_core", use_mag=use_mag))
            rows.append(_row(n, "vqf_core_defaults" + ("" if use_mag else "_6d"), -1, r.errors, r.us_per_sample))
    try:
        for n in names:
            t = loaded[n]
            for use_mag in (True, False) if six_d else (True,):
                q, us = _vqf(t, use_mag)
                rows.append(_row(n, "vqf" if use_mag else "vqf_6d", -1,
                                 trial_errors(q, t.opt_quat, t.movement, six_d=not use_mag), us))
                if use_mag:
                    series[n]["vqf"] = _errors_series(q, t)
    except ImportError:
        log.info("vqf is not installed (pip install -e '.[dev]'): VQF is left out of the comparison")
    return rows


@dataclass
class _Fold:
    """One fold's trials, predictions and models, for its ablations."""

    k: int
    train: list
    test: list
    loaded: dict
    preds: dict  # name -> (N, S + 6): the final models' on test trials, out-of-fold on training trials
    models: object  # CompiledModels
    gains9: object  # the fold's learned 9D toggling settings
    info: dict
    gains: dict  # mode -> the fold's toggling.gains.LearnedGains (run.train.TrainedModels.gains)


def _no_noise(layout: PredictionLayout):
    def transform(p):  # predicted states, no noise removal
        p = p.copy()
        p[:, layout.eta] = np.where(np.isnan(p[:, layout.eta]), np.nan, 0.0)
        return p
    return transform


def _one_state(layout: PredictionLayout):
    def transform(p):  # noise removal with one fixed gain pair, no state, no rest bias
        p = p.copy()
        p[:, layout.probabilities] = 0.0
        p[:, 0] = 1.0
        return p
    return transform


def _ablations(job: _FoldJob, fold: _Fold) -> list:
    """The ablation rows of a fold (module docstring), in table order."""
    cfg, rows = job.cfg, []
    layout = PredictionLayout.of(len(fold.models.class_names))
    if "toggling_only" in cfg.ablations:
        rows += _toggling_variant(job, fold, "toggling_only", _no_noise(layout), cfg.gains, None)
    if "noise_only" in cfg.ablations:
        rows += _toggling_variant(job, fold, "noise_only", _one_state(layout), replace(cfg.gains, bias_tau=(-1.0,)),
                                  replace(fold.gains9, bias_tau=-1.0))
    if "vqf_taus_only" in cfg.ablations:  # the learned time constants without the noise removal
        rows += _vqf_variant(job, fold, "vqf_taus_only", fold.preds)
    if "vqf_oracle" in cfg.ablations:  # the true motion state as the prediction: the ceiling of a better classifier
        label_settings = LabelSettings.from_dict({**job.train_cfg["labels"], "seed": job.train_cfg["run"]["seed"]})
        oracle = {n: oracle_predictions(fold.loaded[n], label_settings, fold.models.class_names)
                  for n in fold.train + fold.test}
        rows += _vqf_variant(job, fold, "vqf_oracle", oracle)
    if "6d" in cfg.ablations:  # gains learned in 6D by `togglecf train`
        s6 = fold.gains["6d"].settings
        rows += _toggling_rows(fold, "toggling_6d", s6, fold.preds, use_mag=False)
    if "ransac_off" in cfg.ablations:
        rows += _ransac_off(job, fold)
    return rows


def _toggling_rows(fold: _Fold, label: str, settings, preds: dict, use_mag: bool = True) -> list:
    """``TogglingFilter`` with ``settings`` fed ``preds`` on the fold's test trials."""
    rows = []
    for n in fold.test:
        t = fold.loaded[n]
        o = TogglingFilter(t.fs, settings, use_mag=use_mag).update_batch(t.gyr, t.acc, t.mag if use_mag else None,
                                                                        predictions=preds[n])
        rows.append(_row(n, label, fold.k, trial_errors(o.quat, t.opt_quat, t.movement, six_d=not use_mag)))
    return rows


def _toggling_variant(job: _FoldJob, fold: _Fold, label: str, transform, search, start) -> list:
    """The toggling CF's gains learned again on transformed predictions, scored on the test trials."""
    preds = {n: transform(fold.preds[n]) for n in fold.train + fold.test}
    s, _ = learn_gains([fold.loaded[n] for n in fold.train], [preds[n] for n in fold.train], fold.models.class_names,
                       fold.models.static_state, use_mag=True, search=search, start=start, jobs=job.jobs)
    if label == "noise_only":  # one gain for all states: the learner only moves state 0's, copy it
        ns = len(fold.models.class_names)
        s = replace(s, tau_acc=(s.tau_acc[0],) * ns, tau_mag=(s.tau_mag[0],) * ns)
    fold.info.setdefault("ablation_gains", {})[label] = {"tau_acc": s.tau_acc, "tau_mag": s.tau_mag}
    return _toggling_rows(fold, label, s, preds)


def _vqf_variant(job: _FoldJob, fold: _Fold, label: str, preds: dict) -> list:
    """The learned VQF's time constants learned on ``preds`` without the noise removal, scored on the
    test trials with the same kind of predictions."""
    s = learn_vqf_variant([fold.loaded[n] for n in fold.train], [preds[n] for n in fold.train],
                          fold.models.class_names, fold.models.static_state, job.cfg.vqf_gains, jobs=job.jobs)
    fold.info.setdefault("ablation_gains", {})[label] = describe_gains(s)
    return [_row(n, label, fold.k, vqf_variant_errors(s, fold.loaded[n], preds[n])) for n in fold.test]


def learn_vqf_variant(trials, predictions, class_names, static_state, search: VQFGainSearch, jobs: int = 1,
                      start=None):
    """The learned VQF's per-state settings (``VQFTogglingSettings``) learned by ``search`` on ``trials``
    fed ``predictions`` (one ``(N, S + 6)`` array per trial: the models', or ``oracle_predictions``),
    without the noise removal (the noise weights held at 0); ``start``: the descent's starting settings
    (default: the core's own, ``search.start``)."""
    search = replace(search, noise_weight_acc=(0.0,), noise_weight_mag=(0.0,))
    s, _ = learn_gains(trials, predictions, class_names, static_state, search=search, start=start, jobs=jobs)
    return s


def vqf_variant_errors(settings, trial, predictions) -> dict:
    """BROAD's errors [deg] (``metrics.trial_errors``) of ``VQFTogglingFilter(settings)`` on ``trial`` (9D)
    fed ``predictions`` ``(N, S + 6)``."""
    o = VQFTogglingFilter(trial.fs, settings).update_batch(trial.gyr, trial.acc, trial.mag, predictions=predictions)
    return trial_errors(o.quat, trial.opt_quat, trial.movement)


def _ransac_off(job: _FoldJob, fold: _Fold) -> list:
    """Models and 9D gains retrained without RANSAC cleaning, scored on the test trials."""
    cfg_off = {s: dict(v) for s, v in job.train_cfg.items()}
    cfg_off["labels"]["ransac"] = False
    cfg_off["gains"]["modes"] = ["9d"]
    cfg_off["run"]["cv_folds"] = job.cfg.inner_folds
    off = run_training(cfg_off, data_dir=job.root, trials=",".join(fold.train),
                       out=_fold_dir(job, fold.k, "models_ransac_off"), cv=True, verbose=False)["trained"]
    t = fold.loaded
    p_off = {n: off.models.predict_samples(t[n].gyr, t[n].acc, t[n].mag, t[n].fs) for n in fold.test}
    return _toggling_rows(fold, "ransac_off", off.gains["9d"].settings, p_off)
