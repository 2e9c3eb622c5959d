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
from togglecf.data.broad import open_index
from togglecf.filters.toggling import TogglingFilter
from togglecf.filters.vqf_toggling import VQFTogglingFilter
from togglecf.learn.compiled import CompiledModels
from togglecf.learn.folds import trial_folds
from togglecf.learn.labels import LabelSettings, make_targets
from togglecf.learn.models import load_bundle
from togglecf.metrics.broad import error_angles_rad, error_quaternion, remove_heading_offset, tagp, trial_errors
from togglecf.registry import TOGGLING, VQF_TOGGLING, FilterSpec
from togglecf.report.study_report import write_report
from togglecf.run.config import GAIN_KEYS, load_config
from togglecf.run.scoring import grid_points, parse_grid, run_filter, score_trial, score_trials
from togglecf.run.sweep import evaluate_trials
from togglecf.run.train import run_training
from togglecf.toggling.gains import GainSearch, VQFGainSearch, describe_gains, learn_gains, load_gains

__all__ = ["StudyConfig", "load_study_config", "run_study"]

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
    (else unchanged). The bracket of BROAD's issue 2 for Madgwick: what a rest-bias calibration
    at start-up gives a filter that does not estimate the bias itself."""
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
    pred = np.zeros((trial.n_samples, len(class_names) + 6))
    valid = targets.valid & (targets.state >= 0)
    pred[np.flatnonzero(valid), targets.state[valid]] = 1.0
    pred[~valid, :len(class_names)] = np.nan
    return pred


def _errors_series(q, t, six_d=False):
    if six_d:
        q = remove_heading_offset(q, t.opt_quat, t.movement)
    return np.degrees(error_angles_rad(error_quaternion(q, t.opt_quat))["total"])


def _baseline_grids(index, names, grids, use_mag, jobs):
    """filter -> (list of params, list over params of trial -> TrialResult)."""
    out = {}
    for filt, grid in grids.items():
        keys = grid_points(grid)
        t0 = time.perf_counter()
        res = evaluate_trials(index, names, filt, keys, use_mag=use_mag, jobs=jobs,
                              desc=f"{filt} grid ({'9D' if use_mag else '6D'})")
        log.info(f"  {filt} {'9D' if use_mag else '6D'}: {len(keys)} grid points x {len(names)} trials "
             f"in {time.perf_counter() - t0:.1f} s")
        out[filt] = (keys, res)
    return out


def _tagp_on(train_names, keys, res):
    """BROAD's TAGP of a grid over the training trials only: (index, params, mean total RMSE)."""
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


def run_study(config: StudyConfig | None = None, data_dir=None, out_dir="reports/study", trials=None) -> dict:
    """Run the whole study and write its report; returns the result tables (see ``report``)."""
    cfg = config or load_study_config()
    jobs = cfg.jobs or os.cpu_count() or 1
    out = Path(out_dir)
    t_start = time.perf_counter()
    index = open_index(data_dir or load_config(cfg.train_config)["run"]["data"] or None)  # --data > [run] data
    names = index.select(trials)
    log.info(index.summary())
    folds = trial_folds(names, cfg.folds, cfg.fold_seed)
    loaded = {n: index.load(n) for n in names}
    timing = {}

    log.info("baselines: evaluating grids on all trials (each fold picks its TAGP on its training trials)")
    t0 = time.perf_counter()
    grids9 = _baseline_grids(index, names, cfg.baselines, True, jobs)
    grids6 = _baseline_grids(index, names, cfg.baselines_6d, False, jobs) if "6d" in cfg.ablations else {}
    timing["baseline_grids_s"] = time.perf_counter() - t0

    rest_bias_grid = {}
    if "madgwick_rest_bias" in cfg.ablations and "madgwick" in cfg.baselines:
        keys = grid_points(cfg.baselines["madgwick"])
        corrected = {n: without_initial_rest_bias(loaded[n]) for n in names}
        rest_bias_grid = {"keys": keys, "res": [{n: score_trial(corrected[n], FilterSpec("madgwick", p))[0]
                                                 for n in names} for p in keys]}
        log.info(f"  madgwick with the initial-rest gyro bias removed: {len(keys)} grid points x {len(names)} trials")

    rows = []  # one per (trial, filter): metrics + fold + params
    series = {n: {} for n in names}  # per-sample total error [deg] for the plots
    timelines = {}
    fold_info = []
    train_cfg = load_config(cfg.train_config)
    six_d = "6d" in cfg.ablations
    train_cfg["gains"].update(learn=True, modes=(["9d", "6d", "vqf_9d", "vqf_6d"] if six_d else ["9d", "vqf_9d"]))
    train_cfg["run"]["cv_folds"] = cfg.inner_folds
    for k, test in enumerate(folds):
        train = [n for n in names if n not in test]
        log.info(f"fold {k + 1}/{len(folds)}: train on {len(train)} trials, test on {', '.join(test)}")
        info = {"fold": k, "train": train, "test": test}
        t0 = time.perf_counter()
        model_dir = out / "folds" / f"fold{k}" / "models"
        res = run_training(train_cfg, data_dir=index.root, trials=",".join(train), out=model_dir, cv=True,
                           verbose=False)  # inner CV, models, then the gains on the CV's out-of-fold predictions
        models = CompiledModels.from_bundle(load_bundle(model_dir))
        gains9 = load_gains(model_dir, use_mag=True)
        info["train_s"] = res["timing"]["final_fit_s"] + res["timing"]["dataset_s"] + res["timing"].get("cv_s", 0.0)
        info["gains_s"] = res["timing"].get("gains_s", 0.0)
        hist = json.loads((model_dir / "gains.json").read_text())["9d"]["history"]
        info["gains"] = {"tau_acc": gains9.tau_acc, "tau_mag": gains9.tau_mag, "output_tau": gains9.output_tau,
                         "bias_tau": gains9.bias_tau, "mag_disturbance_scale": gains9.mag_disturbance_scale,
                         "noise_weight_acc": gains9.noise_weight_acc, "noise_weight_mag": gains9.noise_weight_mag,
                         "confidence_floor": gains9.confidence_floor, "train_objective": hist[-1][2]}
        log.info(f"  models {info['train_s']:.0f} s, gains {info['gains_s']:.0f} s: {info['gains']}")
        # test trials: the fold's final models; training trials: the inner CV's out-of-fold predictions
        preds = {n: models.predict_samples(loaded[n].gyr, loaded[n].acc, loaded[n].mag, loaded[n].fs) for n in test}
        preds.update(res["oof_predictions"])
        spec = FilterSpec(TOGGLING, models=model_dir)  # the headline filter: models compiled into the loop
        for r, o in score_trials([loaded[n] for n in test], spec):
            n, t = r.trial, loaded[r.trial]
            rows.append({"trial": n, "filter": "toggling", "fold": k, "us_per_sample": r.us_per_sample, **r.errors})
            series[n]["toggling"] = _errors_series(o.quat, t)
            timelines[n] = {"alpha_acc": o.diagnostics["alpha_acc"],
                            "p": np.column_stack([o.diagnostics[f"p_{s}"] for s in models.class_names]),
                            "states": models.class_names}
        gains_vqf = load_gains(model_dir, kind=VQF_TOGGLING)  # the VQF core with learned time constants
        info["vqf_gains"] = describe_gains(gains_vqf)
        log.info(f"  learned VQF time constants: {info['vqf_gains']}")
        for r, o in score_trials([loaded[n] for n in test], FilterSpec(VQF_TOGGLING, models=model_dir)):
            rows.append({"trial": r.trial, "filter": "vqf_toggling", "fold": k, "us_per_sample": r.us_per_sample,
                         **r.errors})
            series[r.trial]["vqf_toggling"] = _errors_series(o.quat, loaded[r.trial])
        if six_d:  # the same learned filter in 6D: its own gains (vqf_6d), heading offset removed in the errors
            for r, _ in score_trials([loaded[n] for n in test], FilterSpec(VQF_TOGGLING, models=model_dir,
                                                                           use_mag=False)):
                rows.append({"trial": r.trial, "filter": "vqf_toggling_6d", "fold": k, "us_per_sample": r.us_per_sample,
                             **r.errors})
        _ablations(cfg, k, train, test, loaded, preds, models, gains9, rows, jobs, info, train_cfg, index, out)
        for filt, (keys, res) in grids9.items():
            i, params, train_err = _tagp_on(train, keys, res)
            info.setdefault("baseline_tagp", {})[filt] = {"params": params, "train_mean_total": train_err}
            for n in test:
                r = res[i][n]
                rows.append({"trial": n, "filter": filt, "fold": k, "us_per_sample": r.us_per_sample,
                             "params": json.dumps(params), **r.errors})
                if filt in ("madgwick", "cf"):
                    q, _ = run_filter(loaded[n], FilterSpec(filt, params))
                    series[n][filt] = _errors_series(q.quat, loaded[n])
        if rest_bias_grid:  # BROAD issue 2's bracket: Madgwick at its fold TAGP on rest-bias-corrected gyro
            i, params, _ = _tagp_on(train, rest_bias_grid["keys"], rest_bias_grid["res"])
            for n in test:
                r = rest_bias_grid["res"][i][n]
                rows.append({"trial": n, "filter": "madgwick_rest_bias", "fold": k, "us_per_sample": r.us_per_sample,
                             "params": json.dumps(params), **r.errors})
        for filt, (keys, res) in grids6.items():
            i, params, _ = _tagp_on(train, keys, res)
            for n in test:
                rows.append({"trial": n, "filter": f"{filt}_6d", "fold": k, "us_per_sample": res[i][n].us_per_sample,
                             "params": json.dumps(params), **res[i][n].errors})
        fold_info.append(info)

    for n in names:  # the VQF core (ours, from the paper) at VQF's defaults: the learned filter without learning
        for use_mag in (True, False) if six_d else (True,):
            r, o = score_trial(loaded[n], FilterSpec("vqf_core", use_mag=use_mag))
            rows.append({"trial": n, "filter": "vqf_core_defaults" + ("" if use_mag else "_6d"), "fold": -1,
                         "us_per_sample": r.us_per_sample, **r.errors})

    try:  # VQF: the external state of the art, at its defaults
        for n in names:
            t = loaded[n]
            for use_mag in (True, False) if six_d else (True,):
                q, us = _vqf(t, use_mag)
                rows.append({"trial": n, "filter": "vqf" if use_mag else "vqf_6d", "fold": -1, "us_per_sample": us,
                             **trial_errors(q, t.opt_quat, t.movement, six_d=not use_mag)})
                if use_mag:
                    series[n]["vqf"] = _errors_series(q, t)
    except ImportError:
        log.info("vqf is not installed (pip install -e '.[dev]'): VQF is left out of the comparison")

    timing["total_s"] = time.perf_counter() - t_start
    result = {"rows": rows, "folds": fold_info, "timing": timing, "trials": names, "missing": index.missing,
              "fold_seed": cfg.fold_seed,
              "groups": index.groups}
    write_report(out, result, series, timelines, loaded)
    log.info(f"study done in {timing['total_s']:.0f} s; report in {out}/")
    return result


def _ablations(cfg, k, train, test, loaded, preds, models, gains9, rows, jobs, info, train_cfg, index, out):
    """The ablation variants of fold ``k`` (module docstring)."""
    ns = len(models.class_names)
    variants = {}
    if "toggling_only" in cfg.ablations:  # predicted states, no noise removal
        def no_noise(p):
            p = p.copy()
            p[:, ns:] = np.where(np.isnan(p[:, ns:]), np.nan, 0.0)
            return p
        variants["toggling_only"] = (no_noise, True, cfg.gains)
    if "noise_only" in cfg.ablations:  # noise removal with one fixed gain pair, no state, no rest bias
        def one_state(p):
            p = p.copy()
            p[:, :ns] = 0.0
            p[:, 0] = 1.0
            return p
        variants["noise_only"] = (one_state, True, replace(cfg.gains, bias_tau=(-1.0,)))
    for name, (transform, use_mag, search) in variants.items():
        start = None
        if name == "noise_only":
            start = replace(gains9, bias_tau=-1.0)
        s, hist = learn_gains([loaded[n] for n in train], [transform(preds[n]) for n in train], models.class_names,
                              models.static_state, use_mag=use_mag, search=search, start=start, jobs=jobs)
        if name == "noise_only":  # one gain for all states: the learner only moves state 0's, copy it
            s = replace(s, tau_acc=(s.tau_acc[0],) * ns, tau_mag=(s.tau_mag[0],) * ns)
        info.setdefault("ablation_gains", {})[name] = {"tau_acc": s.tau_acc, "tau_mag": s.tau_mag}
        for n in test:
            t = loaded[n]
            o = TogglingFilter(t.fs, s, use_mag=use_mag).update_batch(t.gyr, t.acc, t.mag if use_mag else None,
                                                                     predictions=transform(preds[n]))
            rows.append({"trial": n, "filter": name, "fold": k, **trial_errors(o.quat, t.opt_quat, t.movement,
                                                                               six_d=not use_mag)})
    no_noise_search = replace(cfg.vqf_gains, noise_weight_acc=(0.0,), noise_weight_mag=(0.0,))
    vqf_variants = {}
    if "vqf_taus_only" in cfg.ablations:  # the learned time constants without the noise removal
        vqf_variants["vqf_taus_only"] = preds
    if "vqf_oracle" in cfg.ablations:  # the true motion state as the prediction: the ceiling of a better classifier
        label_settings = LabelSettings.from_dict({**train_cfg["labels"], "seed": train_cfg["run"]["seed"]})
        vqf_variants["vqf_oracle"] = {n: oracle_predictions(loaded[n], label_settings, models.class_names)
                                      for n in train + test}
    for name, pr in vqf_variants.items():
        s, _ = learn_gains([loaded[n] for n in train], [pr[n] for n in train], models.class_names, models.static_state,
                           search=no_noise_search, jobs=jobs)
        info.setdefault("ablation_gains", {})[name] = describe_gains(s)
        for n in test:
            t = loaded[n]
            o = VQFTogglingFilter(t.fs, s).update_batch(t.gyr, t.acc, t.mag, predictions=pr[n])
            rows.append({"trial": n, "filter": name, "fold": k, **trial_errors(o.quat, t.opt_quat, t.movement)})
    if "6d" in cfg.ablations:  # gains learned in 6D by `togglecf train`
        s6 = load_gains(out / "folds" / f"fold{k}" / "models", use_mag=False)
        for n in test:
            t = loaded[n]
            o = TogglingFilter(t.fs, s6, use_mag=False).update_batch(t.gyr, t.acc, None, predictions=preds[n])
            rows.append({"trial": n, "filter": "toggling_6d", "fold": k,
                         **trial_errors(o.quat, t.opt_quat, t.movement, six_d=True)})
    if "ransac_off" in cfg.ablations:
        cfg_off = {s: dict(v) for s, v in train_cfg.items()}
        cfg_off["labels"]["ransac"] = False
        cfg_off["gains"]["modes"] = ["9d"]
        cfg_off["run"]["cv_folds"] = cfg.inner_folds
        model_dir = out / "folds" / f"fold{k}" / "models_ransac_off"
        run_training(cfg_off, data_dir=index.root, trials=",".join(train), out=model_dir, cv=True, verbose=False)
        m_off = CompiledModels.from_bundle(load_bundle(model_dir))
        s = load_gains(model_dir)
        p_off = {n: m_off.predict_samples(loaded[n].gyr, loaded[n].acc, loaded[n].mag, loaded[n].fs) for n in test}
        for n in test:
            t = loaded[n]
            o = TogglingFilter(t.fs, s).update_batch(t.gyr, t.acc, t.mag, predictions=p_off[n])
            rows.append({"trial": n, "filter": "ransac_off", "fold": k, **trial_errors(o.quat, t.opt_quat, t.movement)})
