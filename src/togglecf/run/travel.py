"""What could set VQF's two time constants on a sensor it never saw: measured before it is built.

The headroom (``run.headroom``) puts the gain over VQF per trial, not per motion state: each trial at its
own τ_acc × τ_mag pair is about 20 % better than VQF's defaults, while a perfect motion-state classifier
adds almost nothing over one tuned pair. This module asks whether anything a filter can see *without a
reference* picks a trial's pair, and whether it travels to a dataset left out.

Every trial of every dataset runs through VQF's core (``filters.vqf_core``) on the τ_acc × τ_mag grid.
Its movement samples are cut in two halves at the middle movement sample. Every row chooses one pair
per trial from the trial's **first half** or from other trials, and is scored on the **second half**
(BROAD's total RMSE [deg], ``metrics.trial_errors``), so that a per-trial choice never sees the samples
it is scored on:

* ``defaults``: VQF's own pair (τ_acc 3 s, τ_mag 9 s).
* ``tagp_other``: the pair best on the *other* datasets (``pair_on``: the worst dataset's mean per-trial
  ln(RMSE / RMSE at the defaults), the learned filters' objective ``toggling.gains.objective_value``).
* ``split_<statistic>``: one trial statistic (``TRIAL_STATISTICS``: physical or normalised by the
  trial's own sensor, computed on its first half) against a threshold, one pair on each side; the
  threshold (a quartile of the other datasets' trials) and both pairs chosen on the other datasets.
* ``self_tuned``: no training at all: the pair whose orientation, carried forward ``horizon_s`` by the
  gyroscope alone, best predicts the accelerometer's gravity and the magnetometer's north on the first
  half's clean samples (``prediction_scores``).
* ``field_change_other``: VQF's own pair with the learned VQF's field-change back-off (step 3b of
  ``filters.vqf_toggling``: nothing learned, the heading correction slowed while the field in the earth frame
  of VQF's 6D estimate changes), its scale σ_f chosen on the *other* datasets (``field_change_on``, the same
  objective as ``tagp_other``) from ``FIELD_CHANGE_SCALES``, the grid the re-learning on one sensor searches
  (``run.config.RELEARN_DEFAULTS``): does a physical rule with one scale in µT travel where a pair does not?
* ``first_half_reference`` (needs the reference, so no filter can do it): the pair best on the trial's
  own first half, scored on its second half: how much of a trial's preference persists in time.
* ``trial_oracle`` (ceiling): the pair best on the second half itself.

Results are per dataset left out (``leave_dataset_out``) and, for comparison, with folds by whole trial
within each dataset (``within_dataset``).
"""
from __future__ import annotations

import logging
import math
import os
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
from numba import njit

from togglecf.core import quaternion as quat
from togglecf.core.io import atomic_write_json, atomic_write_text
from togglecf.core.provenance import generated_line
from togglecf.data.broad import DatasetIndex
from togglecf.filters.base import propagate_gyro
from togglecf.filters.vqf_core import VQFCoreFilter, VQFCoreSettings
from togglecf.filters.vqf_toggling import VQFTogglingFilter, VQFTogglingSettings
from togglecf.learn.folds import trial_folds
from togglecf.metrics.broad import trial_errors
from togglecf.parallel.backend import LocalBackend
from togglecf.run.config import RELEARN_DEFAULTS
from togglecf.run.per_sensor import versus, worst_group
from togglecf.run.study import load_study_config
from togglecf.toggling.gains import objective_value

__all__ = ["TRIAL_STATISTICS", "ROWS", "CEILING_ROWS", "TravelSettings", "travel_settings", "halves",
           "trial_statistics", "gyro_steps", "prediction_scores", "trial_record", "pair_on", "split_rule", "choose_pairs",
           "FIELD_CHANGE_SCALES", "field_change_on", "choose_field_change", "leave_dataset_out", "within_dataset",
           "travel", "travel_table", "travel_json", "run_travel"]

log = logging.getLogger(__name__)

#: the trial statistics a split may use: name -> what it is (all from the trial's first half)
TRIAL_STATISTICS = {
    "acc_norm_dev": "mean | |a| / median |a| − 1 |: how far the specific force strays from gravity (unitless, the "
                    "sensor's own scale)",
    "acc_dev_over_rest_noise": "mean | |a| − median |a| | over the std of |a| at VQF's detected rest (the sensor's own "
                               "noise; NaN without 1 s of rest)",
    "gyr_rms": "RMS of |ω| [rad/s]: how fast the motion is",
    "mag_norm_dev": "median | |m| / median |m| − 1 |: how much the field's magnitude varies (unitless)",
    "dip_std": "std of the dip angle between a and m [deg]",
    "mag_dist_frac": "fraction of samples VQF (at its defaults) flags as magnetically disturbed",
    "rest_frac": "fraction of samples VQF (at its defaults) detects as rest",
}
#: rows every left-out dataset gets, in order; ``split_<statistic>`` rows follow ``tagp_other``
ROWS = ("defaults", "tagp_other", "field_change_other", "self_tuned", "first_half_reference", "trial_oracle")
#: rows that need the reference on the trial itself (ceilings, not filters)
CEILING_ROWS = ("first_half_reference", "trial_oracle")
#: VQF's own pair [s]
DEFAULT_PAIR = (3.0, 9.0)
#: σ_f [µT] of the field-change row (0: off, VQF's defaults): the re-learning's grid, fixed before this row
FIELD_CHANGE_SCALES = tuple(float(v) for v in RELEARN_DEFAULTS["field_change_scale"])
#: first-half samples whose |a| is within this fraction of its median count as clean for the gravity score
_CLEAN_ACC = 0.02
#: ... and whose |m| within this fraction and dip within this angle [deg] of their medians for the north score
_CLEAN_MAG, _CLEAN_DIP_DEG = 0.05, 5.0
#: seconds of rest needed to estimate the accelerometer's noise
_MIN_REST_S = 1.0


@dataclass
class TravelSettings:
    """What ``travel`` computes.

    Attributes:
        tau_acc, tau_mag: the grid [s] (default the study's ``[baselines.vqf_core]``); it must hold
            VQF's defaults (3 s, 9 s).
        horizon_s: how far [s] the self-tuned score carries the orientation by the gyroscope alone.
        folds: folds by whole trial of the within-dataset comparison.
        jobs: worker processes.
    """

    tau_acc: tuple = (1.0, 2.0, 3.0, 4.5, 6.0, 9.0)
    tau_mag: tuple = (5.0, 9.0, 15.0, 30.0)
    horizon_s: float = 1.0
    folds: int = 5
    jobs: int = 1
    pairs: list = field(init=False)

    def __post_init__(self):
        self.pairs = [(float(a), float(m)) for a in self.tau_acc for m in self.tau_mag]
        if DEFAULT_PAIR not in self.pairs:
            raise ValueError(f"the grid must hold VQF's defaults {DEFAULT_PAIR}, got τ_acc {self.tau_acc}, "
                             f"τ_mag {self.tau_mag}")


#: the quick mode's grid (tests, a first look): 2 x 2 around VQF's defaults
QUICK_GRID = {"tau_acc": (1.0, 3.0), "tau_mag": (9.0, 30.0)}


def travel_settings(quick: bool = False, jobs: int | None = None) -> TravelSettings:
    """The study's grid and folds (``configs/study.toml``); ``quick``: a 2 x 2 grid."""
    cfg = load_study_config()
    grid = QUICK_GRID if quick else cfg.baselines["vqf_core"]
    return TravelSettings(tau_acc=tuple(grid["tau_acc"]), tau_mag=tuple(grid["tau_mag"]), folds=cfg.folds,
                          jobs=jobs or os.cpu_count() or 1)


def halves(movement) -> tuple[np.ndarray, np.ndarray]:
    """The first and second half of the scored samples ``movement`` ``(N,)`` bool, cut at the middle
    movement sample; both ``(N,)`` bool (all False when no sample moves)."""
    movement = np.asarray(movement, bool)
    idx = np.flatnonzero(movement)
    if idx.size == 0:
        return movement.copy(), movement.copy()
    before = np.arange(movement.size) < idx[idx.size // 2]
    return movement & before, movement & ~before


def _dip_deg(acc, mag, acc_norm, mag_norm) -> np.ndarray:
    """arcsin(a·m / (|a| |m|)) [deg] ``(N,)``: 90° minus the angle between the specific force and the
    field, the field's dip up to sign (``(N, 3)`` vectors and their norms ``(N,)``)."""
    cos = np.sum(acc * mag, axis=1) / np.maximum(acc_norm * mag_norm, 1e-12)
    return np.degrees(np.arcsin(np.clip(cos, -1.0, 1.0)))


def trial_statistics(trial, rest, mag_dist, first) -> dict:
    """``TRIAL_STATISTICS`` of ``trial`` over the samples ``first`` ``(N,)`` bool; ``rest``, ``mag_dist``:
    VQF's flags per sample at its defaults ``(N,)``."""
    an, mn = np.linalg.norm(trial.acc, axis=1)[first], np.linalg.norm(trial.mag, axis=1)[first]
    dip = _dip_deg(trial.acc[first], trial.mag[first], an, mn)
    a0, m0 = np.nanmedian(an), np.nanmedian(mn)
    at_rest = np.asarray(rest, bool)[first]
    noise = float(np.nanstd(an[at_rest])) if at_rest.sum() >= _MIN_REST_S * trial.fs else math.nan
    return {"acc_norm_dev": float(np.nanmean(np.abs(an / a0 - 1.0))),
            "acc_dev_over_rest_noise": float(np.nanmean(np.abs(an - a0)) / noise) if noise > 0 else math.nan,
            "gyr_rms": float(np.sqrt(np.nanmean(np.sum(trial.gyr[first] ** 2, axis=1)))),
            "mag_norm_dev": float(np.nanmedian(np.abs(mn / m0 - 1.0))),
            "dip_std": float(np.nanstd(dip)),
            "mag_dist_frac": float(np.mean(np.asarray(mag_dist, float)[first])),
            "rest_frac": float(np.mean(at_rest))}


@njit(cache=True)
def _gyro_chain(gyr, dt):
    """The gyroscope's orientation increments chained from the first sample ``(N + 1, 4)``: row k is
    the body rotation from sample 0 to sample k (``G_{k+1} = G_k ⊗ exp(ω_k dt / 2)``, the filters'
    ``propagate_gyro``: a missing or saturated sample adds no rotation)."""
    g = np.empty((gyr.shape[0] + 1, 4))
    q = (1.0, 0.0, 0.0, 0.0)
    g[0] = q
    for k in range(gyr.shape[0]):
        q, _ = propagate_gyro(q, gyr[k], dt, dt)
        g[k + 1] = q
    return g


def gyro_steps(trial, horizon_s: float) -> tuple[int, np.ndarray]:
    """``(h, steps)``: h = ``horizon_s`` · fs samples and, for every sample i ≥ h, the body rotation from
    sample i − h to i by the gyroscope alone ``(N − h, 4)`` (empty when the trial is shorter)."""
    h = max(1, int(round(horizon_s * trial.fs)))
    chain = _gyro_chain(np.ascontiguousarray(trial.gyr, np.float64), 1.0 / trial.fs)
    i = np.arange(h, trial.gyr.shape[0])
    # the estimate at a sample has integrated that sample's rate (as every filter here): samples i − h + 1 .. i
    return h, quat.multiply(quat.conjugate(chain[i - h + 1]), chain[i + 1])


def prediction_scores(q_est, trial, steps: tuple[int, np.ndarray], mask) -> tuple[float, float]:
    """Reference-free scores [rad²] of an estimate ``q_est`` ``(N, 4)`` (sensor to ENU) of ``trial``:
    the orientation at sample i − h carried to sample i by the gyroscope alone (``steps``, from
    ``gyro_steps``) predicts gravity and north; the mean squared angle between the predicted up and the
    measured acceleration where |a| is within 2 % of its median, and the mean squared heading of the
    measured field from north where |m| is within 5 % and the dip within 5° of their medians, over the
    samples of ``mask`` ``(N,)`` bool. NaN where no sample qualifies."""
    h, step = steps
    i = np.arange(h, q_est.shape[0])
    q_pred = quat.multiply(q_est[i - h], step)
    acc, mag = trial.acc[i], trial.mag[i]
    an, mn = np.linalg.norm(acc, axis=1), np.linalg.norm(mag, axis=1)
    dip = _dip_deg(acc, mag, an, mn)
    keep = np.asarray(mask, bool)[i] & np.isfinite(q_pred[:, 0])
    clean_acc = keep & (np.abs(an / np.nanmedian(an) - 1.0) < _CLEAN_ACC)
    clean_mag = (keep & (np.abs(mn / np.nanmedian(mn) - 1.0) < _CLEAN_MAG)
                 & (np.abs(dip - np.nanmedian(dip)) < _CLEAN_DIP_DEG))
    up = quat.rotate(quat.conjugate(q_pred[clean_acc]), np.array([0.0, 0.0, 1.0]))
    cos_a = np.sum(up * acc[clean_acc], axis=1) / an[clean_acc]
    field_enu = quat.rotate(q_pred[clean_mag], mag[clean_mag])
    heading = np.arctan2(field_enu[:, 0], field_enu[:, 1])  # ENU: north is +y, east +x
    score_acc = float(np.mean(np.arccos(np.clip(cos_a, -1.0, 1.0)) ** 2)) if clean_acc.any() else math.nan
    score_mag = float(np.mean(heading ** 2)) if clean_mag.any() else math.nan
    return score_acc, score_mag


def _append_totals(rec: dict, q_est, trial, first, second) -> None:
    """Append to ``rec``'s ``"whole"``, ``"first"``, ``"second"`` lists the total RMSE [deg] of ``q_est``
    ``(N, 4)`` on the trial's movement samples and on its two halves (``halves``)."""
    for key, mask in (("whole", trial.movement), ("first", first), ("second", second)):
        rec[key].append(float(trial_errors(q_est, trial.opt_quat, mask)["total"]))


def trial_record(root, name: str, settings: TravelSettings) -> dict:
    """One trial of the dataset at ``root`` on the grid: ``"groups"``; ``"stats"`` (``TRIAL_STATISTICS``);
    per pair (``settings.pairs`` order) the total RMSE [deg] on the whole trial (``"whole"``), its first
    (``"first"``) and second half (``"second"``), and the reference-free scores on the first half
    (``"score_acc"``, ``"score_mag"`` [rad²], ``prediction_scores``); ``"field_change"``: the same three
    RMSEs per σ_f of ``FIELD_CHANGE_SCALES`` at VQF's own pair (σ_f 0: that pair's own values)."""
    index = DatasetIndex.from_dir(root)
    trial = index.load(name)
    first, second = halves(trial.movement)
    rec = {k: [] for k in ("whole", "first", "second", "score_acc", "score_mag")}
    steps = gyro_steps(trial, settings.horizon_s)
    for tau_acc, tau_mag in settings.pairs:
        out = VQFCoreFilter(trial.fs, replace(VQFCoreSettings(), tau_acc=tau_acc, tau_mag=tau_mag)).update_batch(
            trial.gyr, trial.acc, trial.mag)
        _append_totals(rec, out.quat, trial, first, second)
        score_acc, score_mag = prediction_scores(out.quat, trial, steps, first)
        rec["score_acc"].append(score_acc)
        rec["score_mag"].append(score_mag)
        if (tau_acc, tau_mag) == DEFAULT_PAIR:
            d = out.diagnostics
            stats = trial_statistics(trial, d["rest"] > 0.5, d["mag_dist"] > 0.5, first)
    default = settings.pairs.index(DEFAULT_PAIR)
    field_change = {key: [] for key in ("whole", "first", "second")}
    for scale in FIELD_CHANGE_SCALES:
        if scale == 0.0:  # off: the core at VQF's pair, already run
            for key in field_change:
                field_change[key].append(rec[key][default])
            continue
        out = VQFTogglingFilter(trial.fs, VQFTogglingSettings(tau_acc=DEFAULT_PAIR[0], tau_mag=DEFAULT_PAIR[1],
                                                              field_change_scale=scale)).update_batch(
            trial.gyr, trial.acc, trial.mag)
        _append_totals(field_change, out.quat, trial, first, second)
    return {"groups": list(index.trial_groups(name)), "stats": stats, **rec, "field_change": field_change}


def _best_column(whole, default: int, names) -> int:
    """The column of ``whole`` ``(len(names), k)`` [deg] with the least worst dataset's mean per-trial
    ln(RMSE / RMSE in column ``default``) (``objective_value``)."""
    datasets = np.array([n.partition("/")[0] for n in names])
    values = [objective_value("worst_dataset_log_ratio", whole[:, i], whole[:, default], datasets)
              for i in range(whole.shape[1])]
    return int(np.nanargmin(values))


def pair_on(records: dict, names, pairs) -> int:
    """The index into ``pairs`` best over the trials ``names`` of ``records`` (``"<dataset>/<trial>"`` ->
    ``trial_record``) on their whole trials: the worst dataset's mean per-trial ln(RMSE / RMSE at VQF's
    defaults) (``objective_value``); VQF's defaults when ``names`` is empty."""
    default = pairs.index(DEFAULT_PAIR)
    if not names:
        return default
    return _best_column(np.array([records[n]["whole"] for n in names]), default, names)


def field_change_on(records: dict, names) -> int:
    """The index into ``FIELD_CHANGE_SCALES`` best over the trials ``names`` on their whole trials, with
    ``pair_on``'s objective against σ_f 0 (VQF's defaults); 0 (off) when ``names`` is empty."""
    off = FIELD_CHANGE_SCALES.index(0.0)
    if not names:
        return off
    return _best_column(np.array([records[n]["field_change"]["whole"] for n in names]), off, names)


def choose_field_change(records: dict, train, test) -> tuple[dict, float]:
    """The field-change row: ``({trial of test: {"total": its second-half RMSE [deg]}}, σ_f [µT])``, σ_f
    chosen on ``train`` (``field_change_on``)."""
    i = field_change_on(records, train)
    return {n: {"total": records[n]["field_change"]["second"][i]} for n in test}, FIELD_CHANGE_SCALES[i]


def split_rule(records: dict, names, statistic: str, pairs) -> dict | None:
    """The split of ``names`` by ``statistic`` best on them (``pair_on``'s objective over the trials at
    their side's pair): the threshold among the quartiles of the statistic over ``names``, the pair
    below or at it and the pair above. ``None`` when no quartile leaves three trials on each side.
    A trial whose statistic is NaN takes VQF's defaults."""
    x = np.array([records[n]["stats"][statistic] for n in names], np.float64)
    default = pairs.index(DEFAULT_PAIR)
    best = None
    for q in (0.25, 0.5, 0.75):
        if not np.isfinite(x).any():
            break
        th = float(np.nanquantile(x, q))
        low = [n for n, v in zip(names, x) if v <= th]
        high = [n for n, v in zip(names, x) if v > th]
        if min(len(low), len(high)) < 3:
            continue
        rule = {"statistic": statistic, "threshold": th, "low": pair_on(records, low, pairs),
                "high": pair_on(records, high, pairs)}
        chosen = {n: _split_choice(rule, records[n], default) for n in names}
        whole = np.array([records[n]["whole"][chosen[n]] for n in names])
        start = np.array([records[n]["whole"][default] for n in names])
        value = objective_value("worst_dataset_log_ratio", whole, start,
                                np.array([n.partition("/")[0] for n in names]))
        if best is None or value < best[0]:
            best = (value, rule)
    return None if best is None else best[1]


def _split_choice(rule: dict, record: dict, default: int) -> int:
    v = record["stats"][rule["statistic"]]
    return default if not math.isfinite(v) else rule["low"] if v <= rule["threshold"] else rule["high"]


def _own_choice(record: dict, key: str, default: int) -> int:
    """The pair best on one of the trial's own columns (``default`` when every value is NaN)."""
    values = np.asarray(record[key], np.float64)
    return int(np.nanargmin(values)) if np.isfinite(values).any() else default


def _self_tuned_choice(record: dict, default: int) -> int:
    """The pair with the least sum of the two reference-free scores (a score no sample qualified for
    counts 0; VQF's defaults when neither has one)."""
    acc, mag = (np.asarray(record[k], np.float64) for k in ("score_acc", "score_mag"))
    if not (np.isfinite(acc).any() or np.isfinite(mag).any()):
        return default
    return int(np.argmin(np.nan_to_num(acc, nan=0.0) + np.nan_to_num(mag, nan=0.0)))


def choose_pairs(records: dict, train, test, pairs) -> tuple[dict, dict]:
    """Every row's pair (an index into ``pairs``) for each trial of ``test``, chosen on ``train`` (other
    trials) or on the test trial's first half. Returns ``(rows, rules)``: row -> trial -> index, and
    row -> the rule chosen on ``train`` (the pair, or the split). The field-change row is not a pair:
    ``choose_field_change``."""
    default = pairs.index(DEFAULT_PAIR)
    tagp = pair_on(records, train, pairs)
    rows = {"defaults": {n: default for n in test}, "tagp_other": {n: tagp for n in test}}
    rules = {"tagp_other": list(pairs[tagp])}
    for stat in TRIAL_STATISTICS:
        rule = split_rule(records, train, stat, pairs)
        if rule is not None:
            rows[f"split_{stat}"] = {n: _split_choice(rule, records[n], default) for n in test}
            rules[f"split_{stat}"] = {**rule, "low": list(pairs[rule["low"]]), "high": list(pairs[rule["high"]])}
    for n in test:
        r = records[n]
        rows.setdefault("self_tuned", {})[n] = _self_tuned_choice(r, default)
        rows.setdefault("first_half_reference", {})[n] = _own_choice(r, "first", default)
        rows.setdefault("trial_oracle", {})[n] = _own_choice(r, "second", default)
    return rows, rules


def _scored(records: dict, rows: dict) -> dict:
    """row -> trial -> {"total": second-half RMSE [deg]} at each trial's chosen pair."""
    return {row: {n: {"total": records[n]["second"][i]} for n, i in per.items()} for row, per in rows.items()}


def _scored_names(records: dict, pairs, dataset: str) -> list:
    """The trials of ``dataset`` whose second half has a score at VQF's defaults (a trial without one,
    e.g. a reference missing over its second half, cannot be compared)."""
    default = pairs.index(DEFAULT_PAIR)
    return sorted(n for n, r in records.items()
                  if n.partition("/")[0] == dataset and math.isfinite(r["second"][default]))


def leave_dataset_out(records: dict, pairs) -> dict:
    """Per dataset: every row chosen on the other datasets' trials (or the trial's first half), scored on
    the dataset's second halves: ``{"rows": row -> trial -> {"total"}, "rules": ...}``."""
    datasets = sorted({n.partition("/")[0] for n in records})
    out = {}
    for ds in datasets:
        test = _scored_names(records, pairs, ds)
        train = sorted(n for n in records if n.partition("/")[0] != ds)
        rows, rules = choose_pairs(records, train, test, pairs)
        scored = _scored(records, rows)
        scored["field_change_other"], rules["field_change_other"] = choose_field_change(records, train, test)
        out[ds] = {"rows": scored, "rules": rules}
    return out


def within_dataset(records: dict, pairs, folds: int) -> dict:
    """Per dataset: folds by whole trial within it (``learn.folds.trial_folds``, round robin), every row
    chosen on the fold's training trials, scored on its test trials' second halves."""
    out = {}
    for ds in sorted({n.partition("/")[0] for n in records}):
        names = _scored_names(records, pairs, ds)
        rows: dict = {}
        for test in trial_folds(names, min(folds, len(names)), 0):
            train = [n for n in names if n not in test]
            chosen, _ = choose_pairs(records, train, list(test), pairs)
            for row, per in _scored(records, chosen).items():
                rows.setdefault(row, {}).update(per)
            rows.setdefault("field_change_other", {}).update(choose_field_change(records, train, list(test))[0])
        out[ds] = {"rows": rows}
    return out


def travel(dirs, settings: TravelSettings) -> dict:
    """Every trial of every dataset directory of ``dirs`` (BROAD's layout) on the grid (``trial_record``),
    then ``leave_dataset_out`` and ``within_dataset``. Returns ``{"pairs", "records", "groups",
    "left_out", "within", "horizon_s"}``."""
    tasks, groups = [], {}
    for d in dirs:
        index = DatasetIndex.from_dir(d)
        groups[index.root.name] = {g: [f"{index.root.name}/{n}" for n in m] for g, m in sorted(index.groups.items())}
        tasks += [(f"{index.root.name}/{n}", (str(index.root), n, settings)) for n in index.select(None)]
    log.info(f"travel: {len(tasks)} trials x {len(settings.pairs)} pairs of VQF's time constants")
    records = {}
    for outcome in LocalBackend(settings.jobs).run(trial_record, tasks, desc="trials", unit="trial"):
        if outcome.error is not None:
            raise outcome.error
        records[outcome.key] = outcome.value
    records = dict(sorted(records.items()))
    return {"pairs": [list(p) for p in settings.pairs], "records": records, "groups": groups,
            "left_out": leave_dataset_out(records, settings.pairs),
            "within": within_dataset(records, settings.pairs, settings.folds), "horizon_s": settings.horizon_s}


def _row_order(rows: dict) -> list:
    splits = sorted(r for r in rows if r.startswith("split_"))
    return [r for r in ("defaults", "tagp_other") if r in rows] + splits + [r for r in ROWS[2:] if r in rows]


def _pair(p) -> str:
    return f"({p[0]:g} s, {p[1]:g} s)"


def _rule_text(rule) -> str:
    if rule is None:
        return ""
    if isinstance(rule, float):  # the field-change row's σ_f
        return f"σ_f {rule:g} µT at {_pair(DEFAULT_PAIR)}" if rule > 0.0 else f"σ_f 0 (off): {_pair(DEFAULT_PAIR)}"
    if isinstance(rule, list):
        return _pair(rule)
    return f"≤ {rule['threshold']:.3g}: {_pair(rule['low'])}, else {_pair(rule['high'])}"


_HOW = {"defaults": "VQF's own", "self_tuned": "the trial's first half, no reference",
        "first_half_reference": "the trial's first half, with the reference (a ceiling)",
        "trial_oracle": "the second half itself (a ceiling)"}


def travel_table(result: dict, command: str) -> str:
    """Markdown: per dataset left out, every row's mean second-half total RMSE [°] against VQF's defaults
    (relative change, wins / ties / losses, Wilcoxon p; the worst group), the rule chosen on the other
    datasets; then the same rows with folds within each dataset."""
    lines = [generated_line(command), "",
             "Can anything a filter sees without a reference choose VQF's τ_acc × τ_mag per trial, on a dataset "
             "it never saw? Every trial runs through VQF's core on the grid "
             f"({len(result['pairs'])} pairs); each row picks a pair per trial from the trial's **first half** or "
             "from other trials, and is scored on the trial's **second half** of movement samples (BROAD's total "
             "RMSE [°]). `split_<statistic>`: one statistic of the trial's first half against a threshold, a pair "
             "on each side, all chosen on the training trials; `self_tuned`: the pair whose orientation, carried "
             f"{result['horizon_s']:g} s forward by the gyroscope alone, best predicts gravity and north on the "
             "first half's clean samples; `field_change_other`: VQF's own pair with the learned VQF's field-change "
             "back-off (nothing learned: the heading correction slowed while the field in the earth frame of VQF's "
             "6D estimate changes), its scale σ_f chosen on the training trials from "
             f"{', '.join(f'{v:g}' for v in FIELD_CHANGE_SCALES)} µT (the re-learning's grid). "
             "*vs VQF*: relative change of the mean, wins / ties / losses per trial, "
             "two-sided Wilcoxon p; *worst group*: the group (≥ 2 trials) where the row does worst against VQF.", "",
             "| statistic | what it is |", "|---|---|"]
    lines += [f"| `{k}` | {v} |" for k, v in TRIAL_STATISTICS.items()] + [""]
    for ds, res in result["left_out"].items():
        rows, rules = res["rows"], res["rules"]
        ref = rows["defaults"]
        names = sorted(ref)
        unscored = sum(1 for n in result["records"] if n.partition("/")[0] == ds) - len(names)
        lines += [f"## Left out: {ds} ({len(names)} trials; chosen on the other datasets"
                  + (f"; {unscored} without a scored second half left out" if unscored else "") + ")", "",
                  "| row | chosen on / rule | mean [°] | vs VQF | worst group |", "|---|---|---|---|---|"]
        for row in _row_order(rows):
            how = _HOW.get(row) or _rule_text(rules.get(row))
            vs = "" if row == "defaults" else versus(rows[row], ref, names)
            worst = "" if row == "defaults" else worst_group(rows[row], ref, result["groups"][ds])
            mean = float(np.mean([rows[row][n]["total"] for n in names]))
            lines.append(f"| `{row}` | {how} | {mean:.2f} | {vs} | {worst} |")
        lines.append("")
    within = result["within"]
    datasets = list(within)
    lines += ["## For comparison: folds within each dataset", "",
              "The same rows, each chosen on the other folds of the same dataset (vs VQF, as above).", "",
              "| row | " + " | ".join(datasets) + " |", "|---" * (len(datasets) + 1) + "|"]
    for row in _row_order(within[datasets[0]]["rows"]):
        cells = [versus(within[d]["rows"][row], within[d]["rows"]["defaults"], sorted(within[d]["rows"]["defaults"]))
                 if row != "defaults" and row in within[d]["rows"] else "" for d in datasets]
        lines.append(f"| `{row}` | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def travel_json(result: dict) -> dict:
    """The table's source: the grid, every trial's record and every row's per-trial second-half RMSE."""
    return {k: result[k] for k in ("pairs", "horizon_s", "groups", "records", "left_out", "within")}


def run_travel(dirs, out_dir, settings: TravelSettings, command: str) -> dict:
    """``travel`` on ``dirs``, written to ``out_dir/travel.md`` (``travel_table``) and ``out_dir/travel.json``
    (``travel_json``), both atomically. Returns the result."""
    if len(dirs) < 2:
        raise ValueError(f"leaving a dataset out needs at least two datasets, got {len(dirs)}")
    result = travel(dirs, settings)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    atomic_write_json(out / "travel.json", travel_json(result))
    atomic_write_text(out / "travel.md", travel_table(result, command))
    return result
