"""What a fold of the held-out study (``run.study``) scores: its rows of ``per_trial.csv``.

* the learned rows (``LEARNED_ROWS``): each learned filter on the fold's test trials with the fold's
  models compiled into the loop (``score_learned``);
* the baseline rows: each classic filter at its TAGP on the fold's training trials (``tagp_on``,
  ``baseline_rows``), Madgwick on trials with their initial-rest gyro bias removed
  (``rest_bias_grid``), and the filters at their defaults on every trial (``default_rows``: the VQF
  core, VQF itself when installed);
* the ablation rows (``ablation_rows``; same folds, same models, predictions fed to
  ``TogglingFilter``): ``toggling_only`` (η̂ = 0), ``noise_only`` (one gain for all states, no rest
  bias), ``6d`` (no magnetometer, gains learned in 6D), ``ransac_off`` (models retrained without
  RANSAC cleaning), ``vqf_taus_only`` (the learned VQF's time constants without the noise removal),
  ``vqf_oracle`` (the true motion state as the prediction).
"""
from __future__ import annotations

import json
import logging
import time
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from togglecf.filters.prediction import PredictionLayout
from togglecf.filters.toggling import TogglingFilter
from togglecf.filters.vqf_toggling import VQFTogglingFilter
from togglecf.learn.labels import LabelSettings, make_targets
from togglecf.metrics.broad import error_angles_rad, error_quaternion, remove_heading_offset, tagp, trial_errors
from togglecf.registry import TOGGLING, VQF_TOGGLING, FilterSpec
from togglecf.run.scoring import grid_points, run_built, score_trial
from togglecf.run.train import TrainedModels, run_training
from togglecf.toggling.gains import VQFGainSearch, describe_gains, learn_gains, mode_name
from togglecf.toggling.load import IN_LOOP

__all__ = ["LearnedRow", "LEARNED_ROWS", "PLOTTED_BASELINES", "FoldData", "score_learned", "baseline_rows",
           "chosen_params", "rest_bias_grid", "default_rows", "ablation_rows", "errors_series", "tagp_on",
           "oracle_predictions", "without_initial_rest_bias", "learn_vqf_variant", "vqf_variant_errors"]

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


def errors_series(q, t, six_d=False) -> np.ndarray:
    """The total error [deg] per sample ``(N,)`` of the orientations ``q`` ``(N, 4)`` against trial ``t``'s
    optical reference (heading offset removed first when ``six_d``): what the study's plots show."""
    if six_d:
        q = remove_heading_offset(q, t.opt_quat, t.movement)
    return np.degrees(error_angles_rad(error_quaternion(q, t.opt_quat))["total"])


def tagp_on(train_names, keys, res):
    """BROAD's TAGP of a grid over the named trials only (a fold's training trials): ``keys`` the grid's
    parameter dicts, ``res[i]`` trial -> ``TrialResult`` of ``keys[i]``. Returns (index into ``keys``, its
    parameters, their mean total RMSE [deg] over ``train_names``)."""
    grid = {k: list(dict.fromkeys(p[k] for p in keys)) for k in keys[0]}
    t = tagp(grid, {tuple(p.values()): {n: r[n].errors for n in train_names} for p, r in zip(keys, res)})
    i = keys.index(t.params)
    return i, keys[i], float(np.nanmin(t.mean_total))


def _vqf(trial, use_mag=True):
    """VQF (the ``vqf`` package) at its defaults on ``trial``: orientations ``(N, 4)`` (9D, or 6D without
    ``use_mag``) and µs per sample."""
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


def score_learned(spec: LearnedRow, trials, trained: TrainedModels, k: int, out: dict) -> None:
    """The rows of ``spec`` on a fold's test ``trials`` (the fold's models, in memory, compiled into the
    loop with the learned settings of the row's mode), appended to ``out["rows"]`` (fold ``k``); a plotted
    row's error series [deg] ``(N,)`` into ``out["series"][trial][label]`` and the toggling CF's timeline
    (``alpha_acc`` ``(N,)``, state probabilities ``p`` ``(N, S)``, ``states``) into ``out["timelines"][trial]``."""
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
        out["series"][t.name][spec.label] = errors_series(o.quat, t)
        if spec.filter == TOGGLING:
            out["timelines"][t.name] = {"alpha_acc": o.diagnostics["alpha_acc"],
                                        "p": np.column_stack([o.diagnostics[f"p_{s}"] for s in class_names]),
                                        "states": class_names}


def baseline_rows(grids: dict, train, test, k: int, info: dict, suffix: str = "") -> list:
    """Each grid's TAGP on the fold's training trials, scored on its test trials (rows ``filter + suffix``,
    fold ``k``). ``grids``: filter -> (list of parameter dicts, list over them of trial -> ``TrialResult``);
    the chosen parameters and their mean total RMSE [deg] on ``train`` go into ``info["baseline_tagp"]``
    (when ``suffix`` is empty: 9D)."""
    rows = []
    for filt, (keys, res) in grids.items():
        i, params, train_err = tagp_on(train, keys, res)
        if not suffix:
            info.setdefault("baseline_tagp", {})[filt] = {"params": params, "train_mean_total": train_err}
        rows += [_row(n, filt + suffix, k, res[i][n].errors, res[i][n].us_per_sample, params) for n in test]
    return rows


def chosen_params(info: dict, filters) -> list:
    """(filter, parameter dict) of the fold's TAGP of each of ``filters`` that has a grid (from the fold's
    ``info["baseline_tagp"]``, filled by ``baseline_rows``)."""
    return [(f, info["baseline_tagp"][f]["params"]) for f in filters if f in info.get("baseline_tagp", {})]


def rest_bias_grid(grid: dict, loaded: dict, names) -> tuple:
    """The bracket of BROAD's tracker (``without_initial_rest_bias``): Madgwick's ``grid`` (name -> values) on
    the trials ``names`` of ``loaded`` (name -> Trial) with their initial-rest gyro bias removed, as
    ``(params list, [trial -> TrialResult] per point)``."""
    keys = grid_points(grid)
    corrected = {n: without_initial_rest_bias(loaded[n]) for n in names}
    res = [{n: score_trial(corrected[n], FilterSpec("madgwick", p))[0] for n in names} for p in keys]
    log.info(f"  madgwick with the initial-rest gyro bias removed: {len(keys)} grid points x {len(names)} trials")
    return keys, res


def default_rows(loaded: dict, names, six_d: bool, series: dict) -> list:
    """The filters at their defaults, on every trial (fold -1): the VQF core (ours, from the paper), the
    learned filter without learning, and VQF (the external state of the art) when installed; 6D too when
    ``six_d``. ``loaded``: name -> Trial; VQF's 9D error series [deg] ``(N,)`` go into ``series[trial]["vqf"]``."""
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
                    series[n]["vqf"] = errors_series(q, t)
    except ImportError:
        log.info("vqf is not installed (pip install -e '.[dev]'): VQF is left out of the comparison")
    return rows


@dataclass
class FoldData:
    """One fold's trials, predictions and models, for its ablations (``ablation_rows``)."""

    k: int
    train: list
    test: list
    loaded: dict
    preds: dict  # name -> (N, S + 6): the final models' on test trials, out-of-fold on training trials
    models: object  # CompiledModels
    gains9: object  # the fold's learned 9D toggling settings
    info: dict
    gains: dict  # mode -> the fold's toggling.gains.LearnedGains (run.train.TrainedModels.gains)
    ransac_off_dir: Path  # where the ``ransac_off`` ablation writes its retrained models


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


def ablation_rows(job, fold: FoldData) -> list:
    """The ablation rows of ``fold`` (module docstring), in table order. ``job``: the fold's task settings
    (``run.study``'s fold job): ``cfg`` (the ``StudyConfig``: its ablations, gain searches and inner folds),
    ``train_cfg`` (the fold's ``togglecf train`` config), ``root`` (the data's location) and ``jobs``."""
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


def _toggling_rows(fold: FoldData, label: str, settings, preds: dict, use_mag: bool = True) -> list:
    """``TogglingFilter`` with ``settings`` fed ``preds`` on the fold's test trials."""
    rows = []
    for n in fold.test:
        t = fold.loaded[n]
        o = TogglingFilter(t.fs, settings, use_mag=use_mag).update_batch(t.gyr, t.acc, t.mag if use_mag else None,
                                                                        predictions=preds[n])
        rows.append(_row(n, label, fold.k, trial_errors(o.quat, t.opt_quat, t.movement, six_d=not use_mag)))
    return rows


def _toggling_variant(job, fold: FoldData, label: str, transform, search, start) -> list:
    """The toggling CF's gains learned again on transformed predictions, scored on the test trials."""
    preds = {n: transform(fold.preds[n]) for n in fold.train + fold.test}
    s, _ = learn_gains([fold.loaded[n] for n in fold.train], [preds[n] for n in fold.train], fold.models.class_names,
                       fold.models.static_state, use_mag=True, search=search, start=start, jobs=job.jobs)
    if label == "noise_only":  # one gain for all states: the learner only moves state 0's, copy it
        ns = len(fold.models.class_names)
        s = replace(s, tau_acc=(s.tau_acc[0],) * ns, tau_mag=(s.tau_mag[0],) * ns)
    fold.info.setdefault("ablation_gains", {})[label] = {"tau_acc": s.tau_acc, "tau_mag": s.tau_mag}
    return _toggling_rows(fold, label, s, preds)


def _vqf_variant(job, fold: FoldData, label: str, preds: dict) -> list:
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


def _ransac_off(job, fold: FoldData) -> list:
    """Models and 9D gains retrained without RANSAC cleaning, scored on the test trials."""
    cfg_off = {s: dict(v) for s, v in job.train_cfg.items()}
    cfg_off["labels"]["ransac"] = False
    cfg_off["gains"]["modes"] = ["9d"]
    cfg_off["run"]["cv_folds"] = job.cfg.inner_folds
    off = run_training(cfg_off, data_dir=job.root, trials=",".join(fold.train),
                       out=fold.ransac_off_dir, cv=True, verbose=False)["trained"]
    t = fold.loaded
    p_off = {n: off.models.predict_samples(t[n].gyr, t[n].acc, t[n].mag, t[n].fs) for n in fold.test}
    return _toggling_rows(fold, "ransac_off", off.gains["9d"].settings, p_off)
