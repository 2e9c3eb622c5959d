"""Does a trained filter travel? The cross-dataset protocol of the study.

* ``models_transfer(model_dir, index)``: one model directory (e.g. trained on all of BROAD) scored
  on every trial of another dataset (another sensor, rate and motions: the phone data).
* ``study_transfer(study_dir, index)``: each fold's models of a held-out study scored on *its own
  test trials* read from ``index`` (e.g. the same BROAD trials decimated 3x by ``write_decimated``):
  held out, at another rate.

Beside the trained filters (``registry.TRAINED``) the classic ones run at their documented
defaults (``CLASSIC``: VQF's defaults, Madgwick at its BROAD TAGP β = 0.08, the fixed CF, the EKF).
``transfer_table`` writes the Markdown table (mean total RMSE [°] over all trials and per group,
and each trained filter's fallback fraction, ``learn.ranges``) whose first line names the run.
"""
from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np

from togglecf.core.extras import deferred
from togglecf.core.provenance import generated_line
from togglecf.data.broad import DatasetIndex, Trial
from togglecf.registry import TRAINED, FilterSpec
from togglecf.run.scoring import score_trial

h5py = deferred("h5py", extra="data", what="writing decimated trials (togglecf.run.transfer)")

__all__ = ["CLASSIC", "decimate_trial", "write_decimated", "models_transfer", "study_transfer", "transfer_table",
           "results_json"]

#: the classic filters scored beside the trained ones, at their documented defaults
CLASSIC = ("vqf_core", "madgwick", "cf", "ekf")


def decimate_trial(trial: Trial, factor: int) -> dict:
    """BROAD-layout arrays of ``trial`` at ``fs / factor``: the IMU signals averaged over blocks of
    ``factor`` samples (a sensor with a longer output interval and its own averaging); ``opt_quat``,
    ``opt_pos`` and ``movement`` at each block's last sample (the orientation at the end of the
    averaged interval, as the filters report it). Samples after the last whole block are dropped."""
    if factor < 2:
        raise ValueError(f"decimation factor must be >= 2, got {factor}")
    n = (trial.n_samples // factor) * factor
    out = {}
    for name, arr in (("imu_gyr", trial.gyr), ("imu_acc", trial.acc), ("imu_mag", trial.mag)):
        out[name] = arr[:n].reshape(-1, factor, 3).mean(axis=1)
    out["opt_quat"] = trial.opt_quat[factor - 1:n:factor]
    if trial.opt_pos is not None:
        out["opt_pos"] = trial.opt_pos[factor - 1:n:factor]
    out["movement"] = np.asarray(trial.movement[factor - 1:n:factor], dtype=np.uint8)
    return out


def write_decimated(index: DatasetIndex, dst, factor: int = 3, trials=None, log=None) -> Path:
    """A BROAD-layout copy of ``index``'s trials (``trials``: a selection) at ``fs / factor`` in
    ``dst`` (``trials.json`` copied). Written to a sibling first and renamed: never half-written."""
    dst = Path(dst)
    tmp = dst.with_name(dst.name + ".partial")
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir(parents=True)
    shutil.copy(Path(index.root) / "trials.json", tmp / "trials.json")
    for name in index.select(trials):
        trial = index.load(name)
        arrays = decimate_trial(trial, factor)
        with h5py.File(tmp / f"{name}.hdf5", "w") as f:
            for k, v in arrays.items():
                f.create_dataset(k, data=v, compression="gzip")
            f.attrs["sampling_rate"] = trial.fs / factor
            f.attrs["info"] = f"{name}: every {factor} samples averaged (togglecf.run.transfer.decimate_trial)"
        if log is not None:
            log(f"{name}: {trial.n_samples} -> {len(arrays['imu_gyr'])} samples at {trial.fs / factor:.3f} Hz")
    shutil.rmtree(dst, ignore_errors=True)
    tmp.rename(dst)
    return dst


def _score(index, names, spec) -> dict:
    return {n: score_trial(index.load(n), spec)[0] for n in names}


def _with_classic(index, names, per: dict) -> dict:
    for f in CLASSIC:
        per[f] = _score(index, names, FilterSpec(f))
    return per


def models_transfer(model_dir, index: DatasetIndex, trials=None) -> dict:
    """filter -> trial -> ``TrialResult``: the trained filters of ``model_dir`` and ``CLASSIC`` on
    every selected trial of ``index``."""
    names = index.select(trials)
    per = {f: _score(index, names, FilterSpec(f, models=str(model_dir))) for f in TRAINED}
    return _with_classic(index, names, per)


def study_transfer(study_dir, index: DatasetIndex) -> dict:
    """filter -> trial -> ``TrialResult``: each fold's models of the study in ``study_dir`` on its
    own test trials found in ``index`` (their names must match), and ``CLASSIC`` on the same trials."""
    folds = json.loads((Path(study_dir) / "results.json").read_text())["folds"]
    per = {f: {} for f in TRAINED}
    for fold in folds:
        test = [n for n in fold["test"] if n in index.available]
        model_dir = Path(study_dir) / "folds" / f"fold{fold['fold']}" / "models"
        for f in TRAINED:
            per[f].update(_score(index, test, FilterSpec(f, models=str(model_dir))))
    names = sorted(per[TRAINED[0]])
    if not names:
        raise ValueError(f"none of the test trials of {study_dir} is in {index.root}")
    return _with_classic(index, names, per)


def transfer_table(per: dict, index: DatasetIndex, what: str, command: str,
                   groups=("undisturbed", "mag_disturbed", "disturbed")) -> str:
    """Markdown: mean total RMSE [°] of each filter over all its trials and per group of ``index``
    (those present), and the trained filters' mean fallback fractions (% of the scored samples): out
    of the training range, and (the toggling CF) below the confidence floor."""
    names = sorted(next(iter(per.values())))
    groups = [g for g in groups if g in index.groups]
    cols = ["all"] + groups
    head = " | ".join(f"{c} ({len(names) if c == 'all' else len([n for n in index.groups[c] if n in names])})"
                      for c in cols)
    lines = [generated_line(command, what), "",
             "Mean total RMSE [°]; trained filters with their learned gains, the others at their defaults "
             "(Madgwick at its BROAD TAGP). Fallback: share of the scored samples whose window was out of the "
             "models' training range (``learn.ranges``); low confidence: share where the toggling CF's classifier "
             "was below its confidence floor (both run the filter's fallback).", "",
             f"| filter | {head} | fallback | low confidence |", "|---" * (len(cols) + 3) + "|"]
    for f, res in per.items():
        tot = {n: r.errors["total"] for n, r in res.items()}
        row = [np.mean(list(tot.values()))] + [np.mean([tot[n] for n in index.groups[g] if n in tot]) for g in groups]
        shares = [[r.diagnostics[k] for r in res.values() if k in r.diagnostics] for k in ("fallback", "low_confidence")]
        lines.append(f"| {f} | " + " | ".join(f"{v:.2f}" for v in row) + " | "
                     + " | ".join(f"{100 * np.mean(v):.1f} %" if v else "" for v in shares) + " |")
    return "\n".join(lines) + "\n"


def results_json(per: dict) -> dict:
    """filter -> trial -> {"total", "heading", "inclination", "fallback"?}: the table's source numbers."""
    return {f: {n: {**{k: r.errors[k] for k in ("total", "heading", "inclination")}, **r.diagnostics}
                for n, r in res.items()} for f, res in per.items()}

