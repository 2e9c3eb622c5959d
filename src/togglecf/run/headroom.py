"""The headroom over VQF: how much better than VQF's defaults a causal modulation of VQF's two time
constants can get on a dataset, and where.

For one dataset (a directory in BROAD's layout), every trial is scored (BROAD's total, heading and
inclination RMSE [deg], ``metrics.trial_errors``) with:

* ``defaults``: the VQF core (``vqf_core``) at VQF's defaults (τ_acc 3 s, τ_mag 9 s); the ``vqf``
  package's own online VQF is run beside it as a check (the largest per-trial difference is reported);
* ``tagp_held_out``: the core at the τ_acc × τ_mag pair with the lowest mean total RMSE over each fold's
  *training* trials (BROAD's TAGP; folds by whole trial, ``learn.folds.trial_folds``), scored on the
  fold's test trials;
* ``tagp_in_sample`` (oracle): the dataset-wide TAGP chosen on every trial, scored on the same trials;
* ``group_oracle`` (oracle): per group of ``trials.json``, the pair best on that group's own trials; the
  "all" row takes each trial at the best pair of its group in the finest partition of the trials by
  groups (``finest_partition``);
* ``trial_oracle`` (oracle): each trial at its own best pair;
* ``true_labels``: the learned VQF's per-state settings driven by the *true* motion state
  (``run.study_rows.oracle_predictions``: what a perfect classifier would give), learned by the study's
  search (``[gains.vqf]``, from VQF's defaults) on each fold's training trials, scored on its test
  trials (the study's ``vqf_oracle`` ablation, within this dataset);
* ``true_labels_tagp``: the same, with the descent started at the fold's TAGP and τ_acc, τ_mag searched
  per state over the TAGP grid: the per-state ceiling above the held-out TAGP;
* ``true_disturbance``: VQF's defaults with the learned VQF's magnetic back-off (step 3 of
  ``filters.vqf_toggling``: the heading gain divided by 1 + min((|η_m| / σ_m)², f_reject − 1)) driven by the
  *true* field disturbance η_m (``learn.labels.make_targets``: the measured field minus the reference
  orientation's view of the earth field, where the reference is valid; the magnetometer-noise regressor's
  training target), σ_m chosen from ``HeadroomSettings.disturbance_scales`` on each fold's training
  trials and scored on its test trials: the learned back-off with a perfect regressor of its training
  target, which the true-labels rows (zero predicted noise) leave out. Not a bound: where the target also
  holds a trial's constant heading misalignment (a phone's field), a regressor's estimate from the signals
  can back off better than on the target itself;
* ``field_change``: the same back-off driven by a cue without reference and without learning, the change of
  the measured field over ``FIELD_CHANGE_LAG`` in the earth frame of VQF's 6D estimate (``field_change``: the
  gyroscope explains the field's turning, so an undisturbed field stays at the sensor's floor), σ_m chosen
  from ``disturbance_scales`` as for ``true_disturbance``: how much of the back-off's value a physical cue that
  any sensor computes reaches;
* ``field_change_tagp``: the field-change back-off on top of each fold's held-out TAGP pair (σ_m chosen on
  the fold's training trials at that pair): whether the two parts a re-learning on one sensor could tune
  without a model, the time constants and the back-off's scale, add up;
* ``offline``: the ``vqf`` package's offline (non-causal) VQF at its defaults: the bound no causal
  filter should pass.

The oracle rows choose on the trials they are scored on (in-sample ceilings); every other tuned row is
scored on trials its choice never saw. The pairs are chosen on the total RMSE; heading and inclination
are reported at the chosen pair.

Each dataset's table ends with the rows a learned modulation could reach (``GOAL_ROWS``) against the
per-sensor goal (``goal_check``: at least ``GOAL_MARGIN`` below VQF's defaults and below the held-out TAGP,
no group more than ``GOAL_MARGIN`` above VQF's defaults): where even the true-labels rows miss it, no
motion classifier driving the per-state settings can meet it on that dataset; where the true-disturbance
row meets it, a magnetometer-noise regressor driving the back-off could, and the field-change row says how
much of that a cue without learning reaches.
"""
from __future__ import annotations

import logging
import os
import time
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from togglecf.core import quaternion
from togglecf.core.extras import require
from togglecf.core.io import atomic_write_json, atomic_write_text
from togglecf.core.provenance import generated_line, source_revision
from togglecf.data.broad import DatasetIndex
from togglecf.filters.prediction import PredictionLayout
from togglecf.filters.vqf_core import VQFCoreFilter
from togglecf.filters.vqf_toggling import VQFTogglingSettings
from togglecf.learn.folds import trial_folds
from togglecf.learn.labels import LabelSettings, make_targets, state_names
from togglecf.metrics.broad import trial_errors
from togglecf.parallel.backend import LocalBackend
from togglecf.registry import FilterSpec
from togglecf.run.config import load_config
from togglecf.run.scoring import TrialResult, grid_points, score_trial
from togglecf.run.study import load_study_config
from togglecf.run.study_rows import learn_vqf_variant, oracle_predictions, tagp_on, vqf_variant_errors
from togglecf.run.sweep import run_sweep
from togglecf.toggling.gains import VQFGainSearch, describe_gains

__all__ = ["ROWS", "ORACLE_ROWS", "LABELS", "METRICS", "GOAL_MARGIN", "GOAL_ROWS", "HeadroomSettings",
           "headroom_settings", "finest_partition", "held_out_tagp", "true_disturbance_predictions",
           "field_change", "field_change_predictions", "FIELD_CHANGE_LAG", "back_off_at_tagp",
           "dataset_headroom", "group_mean", "goal_check", "headroom_table", "headroom_json", "run_headroom"]

log = logging.getLogger(__name__)

#: the rows of the table, in order (``defaults`` first: every other is compared with it)
ROWS = ("defaults", "tagp_held_out", "tagp_in_sample", "group_oracle", "trial_oracle", "true_labels",
        "true_labels_tagp", "true_disturbance", "field_change", "field_change_tagp", "offline")
#: rows chosen on the trials they are scored on (in-sample ceilings)
ORACLE_ROWS = ("tagp_in_sample", "group_oracle", "trial_oracle")
#: column headers of the table
LABELS = {"defaults": "VQF defaults", "tagp_held_out": "TAGP held out", "tagp_in_sample": "TAGP in-sample (oracle)",
          "group_oracle": "group oracle", "trial_oracle": "trial oracle", "true_labels": "true labels",
          "true_labels_tagp": "true labels from TAGP", "true_disturbance": "true disturbance",
          "field_change": "field change (no learning)", "field_change_tagp": "field change at TAGP",
          "offline": "offline VQF"}
#: the per-sensor goal's margin (issue "learning that pays off", item 2): at least this fraction below VQF's
#: defaults, below the held-out TAGP, and no group more than this fraction above VQF's defaults
GOAL_MARGIN = 0.05
#: the rows checked against that goal: the tuned pair, the learned parts fed true inputs (true labels, true
#: disturbance: the latter no bound), the oracles of the pair and the non-causal bound
GOAL_ROWS = ("tagp_held_out", "true_labels", "true_labels_tagp", "true_disturbance", "field_change",
             "field_change_tagp", "group_oracle", "trial_oracle", "offline")
#: s: the interval over which ``field_change`` compares the field (chosen once, not searched)
FIELD_CHANGE_LAG = 1.0
#: BROAD's metrics reported (``metrics.trial_errors`` keys, degrees)
METRICS = ("total", "heading", "inclination")
#: the core's filter name (``registry``), run at VQF's defaults when given no parameters
CORE = "vqf_core"


@dataclass
class HeadroomSettings:
    """What ``dataset_headroom`` computes.

    Attributes:
        grid: τ_acc [s] and τ_mag [s] values of the core's grid (``{"tau_acc": [...], "tau_mag": [...]}``;
            default the study's ``[baselines.vqf_core]``).
        folds: number of folds by whole trial (at most the number of trials).
        fold_seed: ``learn.folds.trial_folds``'s seed (0: round-robin over the sorted names, the study's).
        search: the true-label rows' per-state search (default the study's ``[gains.vqf]``).
        labels: the motion labels' settings (default the study's training config's ``[labels]`` and seed).
        disturbance_scales: σ_m [µT] values of the back-off rows (true disturbance, field change; each fold
            takes the best on its training trials). Up to 50 µT: a phone's field is noisier and its best
            back-off gentler (every phone fold chose the top of a grid that ended at 20 µT).
        jobs: worker processes of the grid and the gain searches.
    """

    grid: dict = field(default_factory=dict)
    folds: int = 5
    fold_seed: int = 0
    search: VQFGainSearch = field(default_factory=VQFGainSearch)
    labels: LabelSettings = field(default_factory=LabelSettings)
    disturbance_scales: tuple = (2.0, 5.0, 10.0, 20.0, 50.0)
    jobs: int = 1


#: the quick mode's grid and search (tests, a first look): a 2 x 2 grid around VQF's defaults
QUICK_GRID = {"tau_acc": [1.0, 3.0], "tau_mag": [9.0, 30.0]}


def headroom_settings(quick: bool = False, jobs: int | None = None) -> HeadroomSettings:
    """The study's grid, folds, search and labels (``configs/study.toml`` and its training config);
    ``quick``: a 2 x 2 grid and a one-value-per-coordinate search with τ_acc on two values."""
    cfg = load_study_config()
    train = load_config(cfg.train_config)
    labels = LabelSettings.from_dict({**train["labels"], "seed": train["run"]["seed"]})
    grid = {k: list(v) for k, v in cfg.baselines[CORE].items()}
    search = cfg.vqf_gains
    if quick:
        grid = {k: list(v) for k, v in QUICK_GRID.items()}
        search = replace(search, tau_acc=(1.0, 3.0), confidence_floor=(0.0,), mag_disturbance_scale=(0.0,))
    scales = (5.0, 20.0) if quick else HeadroomSettings.disturbance_scales
    return HeadroomSettings(grid=grid, folds=cfg.folds, fold_seed=cfg.fold_seed, search=search, labels=labels,
                            disturbance_scales=scales, jobs=jobs or os.cpu_count() or 1)


def finest_partition(groups: dict, names) -> list[str]:
    """The groups (of ``groups``: name -> members) that split ``names`` into disjoint parts, chosen
    greedily for many small parts: the smallest groups first, each taken when it overlaps none taken
    before. Empty when they do not cover ``names`` (the "all" row of the group oracle is then the
    in-sample TAGP)."""
    present = {g: set(m) & set(names) for g, m in groups.items()}
    taken, covered = [], set()
    for g in sorted((g for g in present if present[g]), key=lambda g: (len(present[g]), g)):
        if not present[g] & covered:
            taken.append(g)
            covered |= present[g]
    return sorted(taken) if covered == set(names) else []


def _errors(r) -> dict:
    return {m: float(r[m]) for m in METRICS}


def _vqf_package(trial, offline: bool) -> np.ndarray:
    """The ``vqf`` package's 9D quaternion ``(N, 4)`` at its defaults, online or offline."""
    vqf = require("vqf", extra="vqf", what="the vqf package's online check and offline estimate")
    gyr, acc, mag = (np.ascontiguousarray(a, dtype=float) for a in (trial.gyr, trial.acc, trial.mag))
    if offline:
        return vqf.offlineVQF(gyr, acc, mag, 1.0 / trial.fs)["quat9D"]
    return vqf.VQF(1.0 / trial.fs).updateBatch(gyr, acc, mag)["quat9D"]


def _true_label_rows(trials: dict, folds, preds: dict, states, settings: HeadroomSettings, tagp: list) -> tuple:
    """Per fold: the study's search from VQF's defaults and, from the fold's TAGP, τ_acc, τ_mag per
    state on the grid; each learned on the training trials fed ``preds`` (true labels) and scored on
    the test trials. Returns ``(rows, info)``: row -> trial -> errors, and per fold the learned settings."""
    static = next((c for c in ("rest", "static") if c in states), states[0])
    wide = replace(settings.search, tau_acc=tuple(settings.grid["tau_acc"]), tau_mag=tuple(settings.grid["tau_mag"]))
    rows = {"true_labels": {}, "true_labels_tagp": {}}
    info = []
    for k, test in enumerate(folds):
        train = [n for n in trials if n not in test]
        t0 = time.perf_counter()
        p = tagp[k]
        starts = {"true_labels": (settings.search, None),
                  "true_labels_tagp": (wide, VQFTogglingSettings(states=tuple(states),
                                                                 modulation_tau=float(wide.modulation_tau),
                                                                 tau_acc=p["tau_acc"], tau_mag=p["tau_mag"]))}
        fold = {}
        for row, (search, start) in starts.items():
            s = learn_vqf_variant([trials[n] for n in train], [preds[n] for n in train], states, static, search,
                                  jobs=settings.jobs, start=start)
            fold[row] = describe_gains(s)
            rows[row].update({n: _errors(vqf_variant_errors(s, trials[n], preds[n])) for n in test})
        info.append(fold)
        log.info(f"  true labels, fold {k + 1}/{len(folds)} in {time.perf_counter() - t0:.0f} s: "
                 + "; ".join(f"{r}: {v}" for r, v in fold.items()))
    return rows, info


def true_disturbance_predictions(trial, labels: LabelSettings, n_states: int) -> np.ndarray:
    """Prediction rows ``(N, S + 6)`` (``PredictionLayout``) that carry the *true* field disturbance η_m [µT]
    (``make_targets``' ``eta_mag``) where the reference is valid, NaN elsewhere, and no class probabilities
    (NaN: the learned VQF keeps its core's settings) nor accelerometer noise (zero)."""
    targets = make_targets(trial, labels)
    eta = np.full((trial.n_samples, 3), np.nan)
    eta[targets.valid] = targets.eta_mag[targets.valid]
    return _disturbance_predictions(eta, n_states)


def field_change(trial, lag_s: float = FIELD_CHANGE_LAG) -> np.ndarray:
    """How much the measured field changed over the last ``lag_s`` [s] in the earth frame of VQF's 6D
    estimate (the core at its defaults, 6D: causal, no magnetometer): ‖R(q₆(t)) m(t) − R(q₆(t − lag))
    m(t − lag)‖ [µT] ``(N,)``, NaN for the first ``lag_s`` and where a sample is not finite. The 6D
    estimate follows the sensor's turning, so in an undisturbed field this stays at the sensor's floor
    (its noise and the 6D heading's drift over ``lag_s``); a disturbance entering, leaving or moving with
    the sensor raises it. No reference and nothing learned."""
    q6 = VQFCoreFilter(trial.fs, use_mag=False).update_batch(trial.gyr, trial.acc).quat
    field = quaternion.rotate(q6, np.asarray(trial.mag, np.float64))
    lag = max(1, int(round(lag_s * trial.fs)))
    out = np.full(trial.n_samples, np.nan)
    if trial.n_samples > lag:
        out[lag:] = np.linalg.norm(field[lag:] - field[:-lag], axis=1)
    return out


def field_change_predictions(trial, n_states: int) -> np.ndarray:
    """Prediction rows ``(N, S + 6)`` that carry ``field_change`` as the field disturbance's size [µT]
    (η_m = (change, 0, 0): the back-off uses |η_m|), NaN where it is NaN; no class probabilities, no
    accelerometer noise."""
    change = field_change(trial)
    eta = np.zeros((trial.n_samples, 3))
    eta[:, 0] = change
    eta[~np.isfinite(change)] = np.nan
    return _disturbance_predictions(eta, n_states)


def _disturbance_predictions(eta_mag: np.ndarray, n_states: int) -> np.ndarray:
    """Rows of ``PredictionLayout.of(n_states)`` with η_m ``eta_mag (N, 3)`` [µT], η_a zero and the class
    probabilities NaN (the learned VQF keeps its core's settings)."""
    layout = PredictionLayout.of(n_states)
    pred = np.full((len(eta_mag), layout.size), np.nan)
    pred[:, layout.eta_acc] = 0.0
    pred[:, layout.eta_mag] = eta_mag
    return pred


def _disturbance_grid(trials: dict, states, settings: HeadroomSettings, predictions_of,
                      pair: dict | None = None) -> tuple[list, list]:
    """Every trial with VQF's defaults (or the time constants of ``pair``: ``{"tau_acc", "tau_mag"}`` [s])
    and the back-off driven by ``predictions_of(name, trial)`` (prediction rows), at each σ_m of
    ``settings.disturbance_scales``: (keys, res) as ``held_out_tagp`` takes them."""
    keys = [{"mag_disturbance_scale": float(v)} for v in settings.disturbance_scales]
    res = [{} for _ in keys]
    for n, t in trials.items():
        pred = predictions_of(n, t)
        for i, k in enumerate(keys):
            e = vqf_variant_errors(VQFTogglingSettings(states=tuple(states), **(pair or {}), **k), t, pred)
            res[i][n] = TrialResult(n, (), _errors(e), 0.0, t.n_samples, params=k)
    return keys, res


def back_off_at_tagp(trials: dict, folds, states, settings: HeadroomSettings, predictions: dict,
                     tagp: list) -> tuple[dict, list]:
    """The back-off driven by ``predictions`` (trial -> prediction rows) on top of each fold's held-out TAGP
    pair (``tagp[k]``: ``{"tau_acc", "tau_mag"}`` [s]): σ_m chosen on the fold's training trials at that
    pair, scored on its test trials. Returns ``(rows, info)`` as ``held_out_tagp``; the grid of each
    distinct pair is run once."""
    names = list(trials)
    grids, rows, info = {}, {}, []
    for k, test in enumerate(folds):
        pair = {"tau_acc": float(tagp[k]["tau_acc"]), "tau_mag": float(tagp[k]["tau_mag"])}
        key = (pair["tau_acc"], pair["tau_mag"])
        if key not in grids:
            grids[key] = _disturbance_grid(trials, states, settings, lambda n, _: predictions[n], pair)
        fold_rows, fold_info = held_out_tagp(names, [test], *grids[key])
        rows.update(fold_rows)
        info.append({**fold_info[0], "fold": k})
    return rows, info


def held_out_tagp(names, folds, keys, res) -> tuple[dict, list]:
    """Each fold's TAGP on its training trials (``names`` not in the fold), scored on its test trials.

    Args:
        names: the trials.
        folds: test sets (lists of names), e.g. ``learn.folds.trial_folds``.
        keys: the grid's parameter dicts; ``res[i]``: trial -> ``TrialResult`` of ``keys[i]``.
    Returns ``(rows, info)``: trial -> {"total", "heading", "inclination"} [deg] at its fold's pair, and
    per fold ``{"fold", "test", "tagp" (parameters), "train_mean_total" [deg]}``."""
    rows, info = {}, []
    for k, test in enumerate(folds):
        train = [n for n in names if n not in test]
        i, params, train_mean = tagp_on(train, keys, res)
        rows.update({n: _errors(res[i][n].errors) for n in test})
        info.append({"fold": k, "test": list(test), "tagp": params, "train_mean_total": train_mean})
    return rows, info


def dataset_headroom(data_dir, settings: HeadroomSettings, trials=None, store=None) -> dict:
    """Every row of ``ROWS`` on every trial of one dataset (``data_dir``, BROAD's layout; ``trials``: a
    selection, ``DatasetIndex.select``); ``store``: a ``run.sweep.ResultStore`` that keeps the grid's
    results. Returns a dict: ``name``, ``trials``, ``groups`` (name -> present members), ``partition``,
    ``rows`` (row -> trial -> {"total", "heading", "inclination"} [deg]), ``folds`` (per fold its test
    trials, the TAGP pair and its training mean, the true-label settings, the true-disturbance and
    field-change σ_m [µT], the latter at VQF's defaults and at the fold's TAGP),
    ``group_pairs``, ``trial_pairs``, ``label_coverage`` (fraction of samples with a true label), ``vqf_check``
    (largest |Δ| [deg] of the core at its defaults against the ``vqf`` package's online VQF) and ``grid``."""
    t_start = time.perf_counter()
    index = DatasetIndex.from_dir(data_dir)
    names = index.select(trials)
    log.info(f"headroom: {index.root.name}, {len(names)} trials")
    loaded = {n: index.load(n) for n in names}
    keys = grid_points(settings.grid)
    t0 = time.perf_counter()
    res = run_sweep(index, names, CORE, keys, backend=LocalBackend(settings.jobs), store=store,
                    on_error="raise").results
    log.info(f"  {CORE} grid: {len(keys)} points x {len(names)} trials in {time.perf_counter() - t0:.0f} s")
    rows = {r: {} for r in ROWS}
    check = {m: 0.0 for m in METRICS}
    for n, t in loaded.items():
        rows["defaults"][n] = _errors(score_trial(t, FilterSpec(CORE))[0].errors)
        online = trial_errors(_vqf_package(t, offline=False), t.opt_quat, t.movement)
        check = {m: max(check[m], abs(online[m] - rows["defaults"][n][m])) for m in METRICS}
        rows["offline"][n] = _errors(trial_errors(_vqf_package(t, offline=True), t.opt_quat, t.movement))

    folds = trial_folds(names, min(settings.folds, len(names)), settings.fold_seed)
    rows["tagp_held_out"], fold_info = held_out_tagp(names, folds, keys, res)

    i_all, pair_all, _ = tagp_on(names, keys, res)
    rows["tagp_in_sample"] = {n: _errors(res[i_all][n].errors) for n in names}
    groups = {g: [n for n in m if n in loaded] for g, m in sorted(index.groups.items())}
    groups = {g: m for g, m in groups.items() if 0 < len(m) < len(names)}  # "all" is the row of every trial
    group_pairs = {g: tagp_on(m, keys, res)[:2] for g, m in groups.items()}
    group_rows = {g: {n: _errors(res[group_pairs[g][0]][n].errors) for n in m} for g, m in groups.items()}
    partition = finest_partition(groups, names)
    for g in partition:  # the "all" row of the group oracle: each trial at its part's pair
        rows["group_oracle"].update(group_rows[g])
    if not partition:
        rows["group_oracle"] = dict(rows["tagp_in_sample"])
    best = {n: min(range(len(keys)), key=lambda i: res[i][n].errors["total"]) for n in names}
    rows["trial_oracle"] = {n: _errors(res[best[n]][n].errors) for n in names}

    states = list(state_names(settings.labels.label_set))
    preds = {n: oracle_predictions(loaded[n], settings.labels, states) for n in names}
    coverage = float(np.mean(np.concatenate([np.isfinite(p[:, 0]) for p in preds.values()])))
    true_rows, true_info = _true_label_rows(loaded, folds, preds, states, settings, [f["tagp"] for f in fold_info])
    rows.update(true_rows)
    t0 = time.perf_counter()
    d_keys, d_res = _disturbance_grid(loaded, states, settings,
                                      lambda _, t: true_disturbance_predictions(t, settings.labels, len(states)))
    rows["true_disturbance"], d_info = held_out_tagp(names, folds, d_keys, d_res)
    log.info(f"  true disturbance: {len(d_keys)} σ_m x {len(names)} trials in {time.perf_counter() - t0:.0f} s; "
             + ", ".join(f"fold {f['fold'] + 1} σ_m {f['tagp']['mag_disturbance_scale']:g} µT" for f in d_info))
    t0 = time.perf_counter()
    change = {n: field_change_predictions(t, len(states)) for n, t in loaded.items()}
    c_keys, c_res = _disturbance_grid(loaded, states, settings, lambda n, _: change[n])
    rows["field_change"], c_info = held_out_tagp(names, folds, c_keys, c_res)
    rows["field_change_tagp"], ct_info = back_off_at_tagp(loaded, folds, states, settings, change,
                                                       [f["tagp"] for f in fold_info])
    log.info(f"  field change at VQF's defaults and at each fold's TAGP: {len(c_keys)} σ_m x {len(names)} trials "
             f"in {time.perf_counter() - t0:.0f} s")
    for f, extra, d, c, ct in zip(fold_info, true_info, d_info, c_info, ct_info):
        f["true_labels"] = extra
        f["true_disturbance_scale"] = d["tagp"]["mag_disturbance_scale"]
        f["field_change_scale"] = c["tagp"]["mag_disturbance_scale"]
        f["field_change_tagp_scale"] = ct["tagp"]["mag_disturbance_scale"]
    log.info(f"  {index.root.name} done in {time.perf_counter() - t_start:.0f} s")
    return {"name": index.root.name, "trials": names, "groups": groups, "partition": partition, "rows": rows,
            "folds": fold_info, "tagp_in_sample": pair_all,
            "group_pairs": {g: p for g, (_, p) in group_pairs.items()}, "group_rows": group_rows,
            "trial_pairs": {n: keys[best[n]] for n in names}, "label_coverage": coverage,
            "vqf_check": check, "grid": settings.grid}


def group_mean(result: dict, row: str, group: str, metric: str = "total") -> float:
    """Mean ``metric`` [deg] of ``row`` over ``group``'s trials ("all": every trial) of a
    ``dataset_headroom`` result. The group oracle's value of a group is at that group's own pair."""
    if group == "all":
        members, per = result["trials"], result["rows"][row]
    else:
        members = result["groups"][group]
        per = result["group_rows"][group] if row == "group_oracle" else result["rows"][row]
    return float(np.mean([per[n][metric] for n in members]))


def goal_check(result: dict, row: str, margin: float = GOAL_MARGIN) -> dict:
    """``row`` of a ``dataset_headroom`` result against the per-sensor goal, on the total RMSE: the relative
    change of its mean over all trials against ``defaults`` (``vs_defaults``) and against ``tagp_held_out``
    (``vs_tagp``), its worst group against ``defaults`` (``worst_group``, ``worst``: a relative change;
    None without groups) and ``met``: ``vs_defaults <= -margin``, ``vs_tagp < 0`` (the held-out TAGP's own
    row cannot pass: it is the pair it is compared with) and ``worst <= margin``."""
    mean = group_mean(result, row, "all")
    vs_defaults = mean / group_mean(result, "defaults", "all") - 1.0
    vs_tagp = mean / group_mean(result, "tagp_held_out", "all") - 1.0
    worst_group, worst = None, None
    for g in result["groups"]:
        change = group_mean(result, row, g) / group_mean(result, "defaults", g) - 1.0
        if worst is None or change > worst:
            worst_group, worst = g, change
    met = vs_defaults <= -margin and vs_tagp < 0.0 and (worst is None or worst <= margin)
    return {"vs_defaults": vs_defaults, "vs_tagp": vs_tagp, "worst_group": worst_group, "worst": worst,
            "met": bool(met)}


def _change(x: float) -> str:
    return f"{100.0 * x:+.1f} %".replace("-", "−")


def _goal_lines(result: dict) -> list[str]:
    """The table of ``GOAL_ROWS`` against the per-sensor goal (``goal_check``)."""
    lines = [f"**Against the per-sensor goal** (total RMSE: at least {100 * GOAL_MARGIN:g} % below VQF's defaults "
             f"and below the held-out TAGP, no group more than {100 * GOAL_MARGIN:g} % above VQF's defaults; the "
             "oracle rows are ceilings, chosen on the trials they are scored on)", "",
             "| row | vs VQF defaults | vs TAGP held out | worst group vs VQF defaults | goal |",
             "|---|---|---|---|---|"]
    for row in GOAL_ROWS:
        c = goal_check(result, row)
        worst = "" if c["worst"] is None else f"{c['worst_group']} {_change(c['worst'])}"
        tagp = "(itself)" if row == "tagp_held_out" else _change(c["vs_tagp"])
        lines.append(f"| {LABELS[row]} | {_change(c['vs_defaults'])} | {tagp} | {worst} | "
                     f"{'met' if c['met'] else 'not met'} |")
    return lines + [""]


def _pair(p: dict) -> str:
    return f"{p['tau_acc']:g} s, {p['tau_mag']:g} s"


def _cell(value: float, ref: float, row: str) -> str:
    if row == "defaults":
        return f"{value:.2f}"
    return f"{value:.2f} ({100.0 * (value / ref - 1.0):+.1f} %)".replace("-", "−")


def headroom_table(results: list, command: str, revision: str | None = None) -> str:
    """Markdown: per dataset (a ``dataset_headroom`` result) and metric, the mean RMSE [°] of every row
    of ``ROWS`` per group (all trials first), each beside VQF's defaults as the relative change of the
    mean; then the rows that could meet the per-sensor goal against it (``goal_check``) and the pairs each fold
    and group chose. The first line names ``command`` and the code that
    ran (``revision``, default ``core.provenance.source_revision()`` now)."""
    lines = [generated_line(command, revision=revision), "",
             "Mean RMSE [°] (BROAD's metric) over the trials of each group; in brackets the change against "
             "*VQF defaults* (the VQF core at τ_acc 3 s, τ_mag 9 s). *TAGP held out*: the τ_acc × τ_mag pair "
             "with the lowest mean total RMSE on each fold's training trials (folds by whole trial within the "
             "dataset), scored on its test trials. Oracles, chosen on the trials they are scored on (ceilings, "
             "not results): *TAGP in-sample* (one pair for the dataset), *group oracle* (one pair per group; "
             "its *all* row takes each trial at the pair of its group in the finest partition listed below), "
             "*trial oracle* (one pair per trial). *true labels*: the learned VQF's per-state settings driven by "
             "the true motion state instead of a classifier (the study's `vqf_oracle`: its search from VQF's "
             "defaults), learned on each fold's training trials and scored on its test trials; *true labels "
             "from TAGP*: the same search started at the fold's TAGP with τ_acc and τ_mag per state on the "
             "grid. *true disturbance*: VQF's defaults with the learned VQF's magnetic back-off driven by the "
             "true field disturbance |η_m| (from the reference: what a perfect regressor of the magnetometer-noise "
             "model's training target would predict; bounded, as the learned VQF's, by the core's rejection "
             "factor), σ_m chosen on each fold's training trials; not a bound, as that target also holds each "
             "trial's constant heading misalignment. *field change (no learning)*: the same back-off driven by "
             f"how much the measured field changed over the last {FIELD_CHANGE_LAG:g} s in the earth frame of VQF's "
             "6D estimate (no reference, nothing learned: the gyroscope explains the field's turning, a "
             "disturbance coming, going or moving with the sensor it does not), σ_m chosen on each fold's "
             "training trials. *field change at TAGP*: the same cue's back-off on top of each fold's held-out "
             "TAGP pair, σ_m chosen on the fold's training trials at that pair (do the two parts a re-learning "
             "on one sensor could set without a model add up?). *offline VQF*: the `vqf` package's non-causal "
             "estimate at "
             "its defaults. Pairs are chosen on the total RMSE; heading and inclination are at the chosen pair.",
             ""]
    for r in results:
        groups = ["all"] + list(r["groups"])
        grid = ", ".join(f"{k} {{{', '.join(f'{v:g}' for v in vals)}}} s" for k, vals in r["grid"].items())
        chk = r["vqf_check"]
        lines += [f"## {r['name']} ({len(r['trials'])} trials, {len(r['folds'])} folds)", "",
                  f"Grid: {grid}. In-sample TAGP: {_pair(r['tagp_in_sample'])}. True motion labels on "
                  f"{100.0 * r['label_coverage']:.1f} % of the samples (elsewhere the core's own settings). "
                  f"The core at its defaults against the `vqf` package's online VQF: largest per-trial "
                  f"difference {chk['total']:.2g}° total, {chk['heading']:.2g}° heading, "
                  f"{chk['inclination']:.2g}° inclination.", ""]
        for metric in METRICS:
            lines += [f"**{metric.capitalize()} RMSE [°]**", "",
                      "| group | trials | " + " | ".join(LABELS[row] for row in ROWS) + " |",
                      "|---" * (len(ROWS) + 2) + "|"]
            for g in groups:
                n = len(r["trials"]) if g == "all" else len(r["groups"][g])
                ref = group_mean(r, "defaults", g, metric)
                lines.append(f"| {g} | {n} | " + " | ".join(_cell(group_mean(r, row, g, metric), ref, row)
                                                          for row in ROWS) + " |")
            lines.append("")
        lines += _goal_lines(r)
        lines += ["Pairs (τ_acc, τ_mag) chosen on the total RMSE: "
                  + "; ".join(f"fold {f['fold'] + 1} TAGP {_pair(f['tagp'])} (training mean "
                              f"{f['train_mean_total']:.2f}°)" for f in r["folds"]) + ". Group oracle: "
                  + "; ".join(f"{g} {_pair(p)}" for g, p in r["group_pairs"].items()) + ". Finest partition: "
                  + (", ".join(r["partition"]) if r["partition"] else "none (the all row is the in-sample TAGP)")
                  + ". True disturbance, σ_m per fold: "
                  + ", ".join(f"{f['true_disturbance_scale']:g} µT" for f in r["folds"])
                  + ". Field change, σ_m per fold: "
                  + ", ".join(f"{f['field_change_scale']:g} µT" for f in r["folds"]) + "; at TAGP: "
                  + ", ".join(f"{f['field_change_tagp_scale']:g} µT" for f in r["folds"]) + ".", ""]
    return "\n".join(lines)


def headroom_json(results: list) -> dict:
    """The table's source numbers: dataset -> its ``dataset_headroom`` result (rows per trial, folds,
    chosen pairs, checks), with the group means per row and metric under ``means``."""
    out = {}
    for r in results:
        means = {g: {row: {m: group_mean(r, row, g, m) for m in METRICS} for row in ROWS}
                 for g in ["all"] + list(r["groups"])}
        out[r["name"]] = {**r, "means": means}
    return out


def run_headroom(dirs, out_dir, settings: HeadroomSettings, command: str, trials=None, store=None) -> list:
    """``dataset_headroom`` on each directory of ``dirs`` (``trials``: the same selection in each), then
    ``out_dir/headroom.md`` (``headroom_table``, its first line naming ``command``) and ``headroom.json``,
    written atomically. Returns the results."""
    revision = source_revision()  # the code that runs (a commit made during a long run is not it)
    results = [dataset_headroom(d, settings, trials, store) for d in dirs]
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    atomic_write_text(out / "headroom.md", headroom_table(results, command, revision))
    atomic_write_json(out / "headroom.json", headroom_json(results))
    log.info(f"headroom: {out / 'headroom.md'}")
    return results
