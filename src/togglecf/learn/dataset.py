"""Training windows: per trial, targets (labels, RANSAC masks) and causal-window features, one row a window."""
from __future__ import annotations

from dataclasses import asdict, dataclass, field

import numpy as np

from togglecf.core.io import file_sha256
from togglecf.data.broad import DatasetIndex
from togglecf.features.windows import FeatureSettings, trial_features, window_length
from togglecf.learn.labels import LabelSettings, make_targets
from togglecf.parallel.backend import InlineBackend

__all__ = ["WindowData", "trial_windows", "build_dataset", "dataset_settings", "common_rate"]


@dataclass
class WindowData:
    """One row per window (window ending at sample ``end`` of trial ``trials[group]``)."""

    X: np.ndarray
    state: np.ndarray
    eta_acc: np.ndarray
    eta_mag: np.ndarray
    train_mask: np.ndarray
    eval_mask: np.ndarray
    group: np.ndarray
    end: np.ndarray
    trials: list
    window_samples: int | None  # None when the trials' rates differ (windows are in seconds)
    fs: float | None  # the trials' common rate [Hz]; None when they differ (each trial's in ``per_trial``)
    per_trial: dict = field(default_factory=dict)
    settings: dict = field(default_factory=dict)  # label/feature settings and RANSAC it was built with

    def subset(self, names) -> "WindowData":
        """The rows of trials ``names`` (in that order of groups), as if built from them alone."""
        names = list(names)
        missing = [n for n in names if n not in self.trials]
        if missing:
            raise ValueError(f"trials {missing} are not in this dataset")
        old = np.array([self.trials.index(n) for n in names])
        remap = np.full(len(self.trials), -1)
        remap[old] = np.arange(len(names))
        rows = np.flatnonzero(np.isin(self.group, old))
        rows = rows[np.argsort(remap[self.group[rows]], kind="stable")]
        arrays = {k: getattr(self, k)[rows] for k in ("X", "state", "eta_acc", "eta_mag", "train_mask", "eval_mask",
                                                       "end")}
        per_trial = {n: self.per_trial[n] for n in names}
        fs = common_rate([p.get("fs", self.fs) for p in per_trial.values()])
        window_s = self.settings.get("features", {}).get("window_s")
        window_samples = self.window_samples if fs == self.fs else (
            window_length(fs, window_s) if fs is not None and window_s is not None else None)
        return WindowData(**arrays, group=remap[self.group[rows]], trials=names, window_samples=window_samples,
                          fs=fs, per_trial=per_trial, settings=self.settings)


def trial_windows(index: DatasetIndex, name, label_settings, feature_settings, ransac):
    """Targets, masks and features of one trial (a task: runs where the backend puts it, loading the trial
    there from ``index``'s path)."""
    trial = index.load(name)
    t = make_targets(trial, label_settings)
    X, ends = trial_features(trial, feature_settings)
    valid = t.valid[ends]
    inl = t.inlier[ends]
    part = dict(X=X, state=t.state[ends], eta_acc=t.eta_acc[ends], eta_mag=t.eta_mag[ends],
                train_mask=valid & inl if ransac else valid, eval_mask=valid & inl, end=ends)
    counts = np.bincount(t.state[t.valid], minlength=len(t.state_names))
    info = {"n_samples": trial.n_samples, "fs": float(trial.fs), "valid_fraction": float(t.valid.mean()),
            "inlier_fraction": t.inlier_fraction, "n_windows": int(len(ends)), "lin_acc_source": t.lin_acc_source,
            "state_fractions": dict(zip(t.state_names, (counts / max(1, counts.sum())).tolist())),
            "mag_ref": t.mag_ref.tolist(), "file": index.available[name].name,
            "sha256": file_sha256(index.available[name])}
    return part, info, trial.fs


def build_dataset(index: DatasetIndex, names, label_settings: LabelSettings, feature_settings: FeatureSettings,
                  ransac: bool = True, backend=None) -> WindowData:
    """Targets, RANSAC masks and features of every trial in ``names``; one task per trial on ``backend``
    (``togglecf.parallel.backend``; default: this process, in order)."""
    backend = backend or InlineBackend()
    tasks = [(g, (index, name, label_settings, feature_settings, ransac)) for g, name in enumerate(names)]
    done = {}
    for o in backend.run(trial_windows, tasks, desc="targets+features", unit="trial"):
        if o.error is not None:
            raise o.error
        done[o.key] = o.value
    parts = []
    per_trial = {}
    for g, name in enumerate(names):
        part, info, _ = done[g]
        parts.append({**part, "group": np.full(len(part["end"]), g)})
        per_trial[name] = info
    cat = {k: np.concatenate([p[k] for p in parts]) for k in ("X", "state", "eta_acc", "eta_mag", "train_mask",
                                                              "eval_mask", "group", "end")}
    # trials at different rates mix freely: windows, hops and every feature are in seconds (features.windows)
    fs = common_rate([p["fs"] for p in per_trial.values()])
    return WindowData(**cat, trials=list(names), window_samples=None if fs is None else window_length(fs, feature_settings.window_s),
                      fs=fs, per_trial=per_trial, settings=dataset_settings(label_settings, feature_settings, ransac))


def common_rate(rates) -> float | None:
    """The one sampling rate [Hz] of ``rates`` (equal to 1 ppm), or None when they differ."""
    rates = [float(r) for r in rates]
    if rates and all(abs(r - rates[0]) <= 1e-6 * rates[0] for r in rates):
        return rates[0]
    return None


def dataset_settings(label_settings, feature_settings, ransac) -> dict:
    """What a dataset was built with (``WindowData.settings``): reusing it needs the same."""
    return {"labels": label_settings.to_dict(), "features": asdict(feature_settings), "ransac": bool(ransac)}
