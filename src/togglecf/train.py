"""``togglecf train``: targets -> RANSAC cleaning -> features -> cross-validation by trial -> final fit.

Cross-validation uses ``GroupKFold`` with the trial as group: every window of a test trial is
left out of that fold's training. Training windows are those whose end sample has valid
targets (and, with ``ransac = true``, is a RANSAC inlier); test windows are always the valid
RANSAC inliers of the test trials, so switching RANSAC changes the training data only and its
effect can be compared on the same test set.

Baselines: the majority class of the fold's training labels (classifier) and zero noise
(regressors). The final models are fitted on all selected trials and saved with
``models.save_bundle``.
"""
from __future__ import annotations

import platform
import sys
import time
import tomllib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from . import __version__
from .data import DatasetIndex, resolve_data_dir
from .features import FeatureSettings, feature_schema, trial_features, window_length
from .io import atomic_write_text, file_sha256
from .labels import LabelSettings, make_targets, state_names
from .filters.toggling import CompiledModels, hold_predictions
from .models import (ModelBundle, MotionClassifier, NoiseRegressor, classification_metrics, regression_metrics,
                     save_bundle)

__all__ = ["DEFAULT_CONFIG", "load_config", "WindowData", "build_dataset", "make_folds", "cross_validate",
           "run_training", "add_train_parser", "cmd_train", "format_cv_table"]

DEFAULT_CONFIG = Path(__file__).resolve().parents[2] / "pipelines" / "configs" / "default.toml"
_RUN_DEFAULTS = {"name": "default", "seed": 0, "nthread": 2, "cv_folds": 5, "trials": "all", "max_features": 0,
                 # where CV folds and per-trial features run (togglecf.backend): local (this process) or dask
                 "backend": "local", "scheduler": "", "retries": 2, "chunk_size": -1, "distributed_fit": False}
_SECTIONS = ("run", "labels", "features", "classifier", "regressor", "gains")
_GAIN_KEYS = ("learn", "modes")


def load_config(source=None) -> dict:
    """Config dict from a TOML path (or an already parsed dict), defaults filled in, unknown keys refused."""
    if source is None:
        source = DEFAULT_CONFIG
    if isinstance(source, dict):
        raw = {k: dict(v) for k, v in source.items()}
    else:
        with open(source, "rb") as f:
            raw = tomllib.load(f)
    bad = sorted(set(raw) - set(_SECTIONS))
    if bad:
        raise ValueError(f"config: unknown section(s) {bad}; expected {list(_SECTIONS)}")
    cfg = {s: dict(raw.get(s, {})) for s in _SECTIONS}
    unknown = sorted(set(cfg["run"]) - set(_RUN_DEFAULTS))
    if unknown:
        raise ValueError(f"config [run]: unknown key(s) {unknown}; known: {sorted(_RUN_DEFAULTS)}")
    cfg["run"] = {**_RUN_DEFAULTS, **cfg["run"]}
    if cfg["run"]["backend"] not in ("local", "dask"):
        raise ValueError(f"config [run]: backend must be 'local' or 'dask', got {cfg['run']['backend']!r}")
    LabelSettings.from_dict({**cfg["labels"], "seed": cfg["run"]["seed"]})  # validate early
    FeatureSettings.from_dict(cfg["features"])
    from .gains import GainSearch

    GainSearch.from_dict({k: v for k, v in cfg["gains"].items() if k not in _GAIN_KEYS})  # validate early
    for sec, cls in (("classifier", MotionClassifier), ("regressor", NoiseRegressor)):
        allowed = set(cls._param_names()) - {"nthread", "seed", "target"}
        unknown = sorted(set(cfg[sec]) - allowed)
        if unknown:
            raise ValueError(f"config [{sec}]: unknown key(s) {unknown}; known: {sorted(allowed)}")
    return cfg


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
    window_samples: int
    fs: float
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
        return WindowData(**arrays, group=remap[self.group[rows]], trials=names, window_samples=self.window_samples,
                          fs=self.fs, per_trial={n: self.per_trial[n] for n in names}, settings=self.settings)


def _trial_part(index: DatasetIndex, name, label_settings, feature_settings, ransac):
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
    info = {"n_samples": trial.n_samples, "valid_fraction": float(t.valid.mean()),
            "inlier_fraction": t.inlier_fraction, "n_windows": int(len(ends)),
            "state_fractions": dict(zip(t.state_names, (counts / max(1, counts.sum())).tolist())),
            "mag_ref": t.mag_ref.tolist(), "file": index.available[name].name,
            "sha256": file_sha256(index.available[name])}
    return part, info, trial.fs


def build_dataset(index: DatasetIndex, names, label_settings: LabelSettings, feature_settings: FeatureSettings,
                  ransac: bool = True, backend=None) -> WindowData:
    """Targets, RANSAC masks and features of every trial in ``names``; one task per trial on ``backend``
    (``togglecf.backend``; default: this process, in order)."""
    from .backend import InlineBackend

    backend = backend or InlineBackend()
    tasks = [(g, (index, name, label_settings, feature_settings, ransac)) for g, name in enumerate(names)]
    done = {}
    for o in backend.run(_trial_part, tasks, desc="targets+features", unit="trial"):
        if o.error is not None:
            raise o.error
        done[o.key] = o.value
    parts = []
    per_trial = {}
    fs0 = None
    for g, name in enumerate(names):
        part, info, fs = done[g]
        if fs0 is None:
            fs0 = fs
        elif abs(fs - fs0) > 1e-6 * fs0:
            raise ValueError(f"{name}: sampling rate {fs} Hz differs from {fs0} Hz of the other trials")
        parts.append({**part, "group": np.full(len(part["end"]), g)})
        per_trial[name] = info
    cat = {k: np.concatenate([p[k] for p in parts]) for k in ("X", "state", "eta_acc", "eta_mag", "train_mask",
                                                              "eval_mask", "group", "end")}
    return WindowData(**cat, trials=list(names), window_samples=window_length(fs0, feature_settings.window_s),
                      fs=fs0, per_trial=per_trial, settings=_dataset_settings(label_settings, feature_settings, ransac))


def _dataset_settings(label_settings, feature_settings, ransac) -> dict:
    from dataclasses import asdict

    return {"labels": label_settings.to_dict(), "features": asdict(feature_settings), "ransac": bool(ransac)}


def make_folds(group: np.ndarray, n_trials: int, n_splits: int):
    """``[(train_trials, test_trials), ...]`` from ``GroupKFold`` on the trial of every window."""
    from sklearn.model_selection import GroupKFold

    k = max(2, min(int(n_splits), n_trials))
    if n_trials < 2:
        raise ValueError("cross-validation by trial needs at least 2 trials")
    dummy = np.zeros(len(group))
    folds = []
    for tr, te in GroupKFold(n_splits=k).split(dummy, groups=group):
        folds.append((np.unique(group[tr]), np.unique(group[te])))
    return folds


def _models(cfg):
    run = cfg["run"]
    common = {"nthread": int(run["nthread"]), "seed": int(run["seed"])}
    clf = MotionClassifier(**cfg["classifier"], **common)
    regs = {t: NoiseRegressor(target=t, **cfg["regressor"], **common) for t in ("acc", "mag")}
    return clf, regs


def _fit_all(cfg, data: WindowData, rows, schema, class_names):
    """Classifier and regressors on ``rows``. With ``[run] max_features = k`` (0: all), a first
    fit ranks the features (``feature_ranking``) and the models are refitted with only the top
    ``k`` present: the other columns are given as missing, so no tree splits on them (fewer
    features to compute on a microcontroller). The ranking uses the same training rows only."""
    X = data.X[rows]
    k = int(cfg["run"].get("max_features", 0) or 0)
    if 0 < k < X.shape[1]:
        keep = set(feature_ranking(*_fit_models(cfg, X, data, rows, schema, class_names), schema)[:k])
        X = X.copy()
        X[:, [i for i, n in enumerate(schema.names) if n not in keep]] = np.nan
    return _fit_models(cfg, X, data, rows, schema, class_names)


def _fit_models(cfg, X, data: WindowData, rows, schema, class_names):
    clf, regs = _models(cfg)
    clf.fit(X, data.state[rows], schema, class_names)
    regs["acc"].fit(X, data.eta_acc[rows], schema)
    regs["mag"].fit(X, data.eta_mag[rows], schema)
    return clf, regs


def _gain_table(clf, regs, schema) -> dict:
    """Per booster (classifier, acc_x … mag_z): feature -> share of its total split gain."""
    cols = {"classifier": clf.booster_}
    for t, r in regs.items():
        for ax, b in zip("xyz", r.boosters_):
            cols[f"{t}_{ax}"] = b
    table = {}
    for c, b in cols.items():
        gain = b.get_score(importance_type="total_gain")
        total = sum(gain.values()) or 1.0
        table[c] = {n: gain.get(n, 0.0) / total for n in schema.names}
    return table


def feature_ranking(clf, regs, schema) -> list:
    """Feature names, most important first: the gain shares summed over the seven boosters."""
    table = _gain_table(clf, regs, schema)
    return sorted(schema.names, key=lambda n: -sum(t[n] for t in table.values()))


def _evaluate(clf, regs, data: WindowData, train_rows, test_rows, schema, n_classes):
    X = data.X[test_rows]
    proba = clf.predict_proba(X, schema)
    y = data.state[test_rows]
    majority = int(np.argmax(np.bincount(data.state[train_rows], minlength=n_classes)))
    const = np.zeros((len(y), n_classes))
    const[:, majority] = 1.0
    res = {"classifier": classification_metrics(y, proba, n_classes),
           "majority": {**classification_metrics(y, const, n_classes), "class": majority}}
    preds = {"proba": proba}
    for t in ("acc", "mag"):
        yt = getattr(data, f"eta_{t}")[test_rows]
        yp = regs[t].predict(X, schema)
        res[t] = regression_metrics(yt, yp)
        res[f"{t}_zero"] = regression_metrics(yt, np.zeros_like(yt))
        preds[t] = yp
    return res, preds


def _cv_fold(cfg, data: WindowData, i, train_g, test_g, schema, class_names):
    """One CV fold (a task): fit on the training trials' rows, score the held-out ones, and the
    out-of-fold predictions on every window of the held-out trials (for the gains)."""
    train_rows = np.flatnonzero(np.isin(data.group, train_g) & data.train_mask)
    test_rows = np.flatnonzero(np.isin(data.group, test_g) & data.eval_mask)
    t0 = time.perf_counter()
    clf, regs = _fit_all(cfg, data, train_rows, schema, class_names)
    res, preds = _evaluate(clf, regs, data, train_rows, test_rows, schema, len(class_names))
    oof_models = CompiledModels.from_bundle(ModelBundle(clf, regs, schema, {}))
    oof = {}
    for g in test_g:
        rows_g = np.flatnonzero(data.group == g)
        oof[data.trials[g]] = (data.end[rows_g], oof_models.predict_windows(data.X[rows_g]))
    res.update(fold=i, test_trials=[data.trials[g] for g in test_g],
               train_trials=[data.trials[g] for g in train_g], n_train=len(train_rows),
               n_test=len(test_rows), seconds=time.perf_counter() - t0)
    return res, preds, oof


def cross_validate(cfg, data: WindowData, schema, class_names, backend=None):
    """Per-fold and pooled CV metrics; ``folds`` records each fold's train/test trial names.
    Also returns the out-of-fold predictions: trial -> (window ends, prediction rows).

    Each fold is one task on ``backend`` (``togglecf.backend``; default: this process, fold after fold,
    each fold with ``[run] nthread`` XGBoost threads); on Dask the window data is scattered once and
    the folds train on the workers. Results are combined in fold order, so they do not depend on
    where or in which order the folds ran."""
    from .backend import InlineBackend

    n_classes = len(class_names)
    folds = make_folds(data.group, len(data.trials), cfg["run"]["cv_folds"])
    backend = backend or InlineBackend()
    handle = backend.scatter(data)
    tasks = [(i, (cfg, handle, i, train_g, test_g, schema, class_names)) for i, (train_g, test_g) in enumerate(folds)]
    fold_out = {}
    for o in backend.run(_cv_fold, tasks, desc="cross-validation", unit="fold"):
        if o.error is not None:
            raise o.error
        fold_out[o.key] = o.value
    out = {"folds": [], "per_trial": {}}
    oof = {}
    pooled = {"y": [], "proba": [], "const": [], "acc": [], "acc_t": [], "mag": [], "mag_t": []}
    for i, (train_g, test_g) in enumerate(folds):
        res, preds, oof_i = fold_out[i]
        oof.update(oof_i)
        test_rows = np.flatnonzero(np.isin(data.group, test_g) & data.eval_mask)
        out["folds"].append(res)
        for g in test_g:  # held-out numbers of every test trial on its own
            sel = data.group[test_rows] == g
            yt = data.state[test_rows][sel]
            m = classification_metrics(yt, preds["proba"][sel], n_classes)
            pt = {"fold": i, "n": int(sel.sum()), "balanced_accuracy": m["balanced_accuracy"], "f1_macro": m["f1_macro"]}
            for t in ("acc", "mag"):
                ytt = getattr(data, f"eta_{t}")[test_rows][sel]
                r = regression_metrics(ytt, preds[t][sel])
                pt.update({f"{t}_rmse": r["rmse"], f"{t}_r2": r["r2"],
                           f"{t}_rmse_zero": regression_metrics(ytt, np.zeros_like(ytt))["rmse"]})
            out["per_trial"][data.trials[g]] = pt
        pooled["y"].append(data.state[test_rows])
        pooled["proba"].append(preds["proba"])
        c = np.zeros_like(preds["proba"])
        c[:, res["majority"]["class"]] = 1.0
        pooled["const"].append(c)
        for t in ("acc", "mag"):
            pooled[t].append(preds[t])
            pooled[f"{t}_t"].append(getattr(data, f"eta_{t}")[test_rows])
    P = {k: np.concatenate(v) for k, v in pooled.items()}
    out["overall"] = {"classifier": classification_metrics(P["y"], P["proba"], n_classes),
                      "majority": classification_metrics(P["y"], P["const"], n_classes)}
    for t in ("acc", "mag"):
        out["overall"][t] = regression_metrics(P[f"{t}_t"], P[t])
        out["overall"][f"{t}_zero"] = regression_metrics(P[f"{t}_t"], np.zeros_like(P[f"{t}_t"]))
    return out, oof


def _short(name: str) -> str:
    return name.split("_")[0]


def format_cv_table(cv: dict, class_names) -> str:
    head = (f"{'fold':>7} {'test trials':<22} {'n_test':>7} | {'balacc':>6} {'(maj)':>6} {'F1':>6} {'(maj)':>6} "
            f"{'AUC':>6} {'(maj)':>6} | {'accRMSE':>7} {'(zero)':>7} {'R2':>6} {'(zero)':>7} | "
            f"{'magRMSE':>7} {'(zero)':>7} {'R2':>6} {'(zero)':>7}")
    lines = [head, "-" * len(head)]

    def row(label, trials, r, n):
        c, m = r["classifier"], r["majority"]
        a, az, g, gz = r["acc"], r["acc_zero"], r["mag"], r["mag_zero"]
        return (f"{label:>7} {trials:<22} {n:>7d} | {c['balanced_accuracy']:6.3f} {m['balanced_accuracy']:6.3f} "
                f"{c['f1_macro']:6.3f} {m['f1_macro']:6.3f} {c['roc_auc']:6.3f} {m['roc_auc']:6.3f} | "
                f"{a['rmse']:7.3f} {az['rmse']:7.3f} {a['r2']:6.3f} {az['r2']:7.3f} | "
                f"{g['rmse']:7.3f} {gz['rmse']:7.3f} {g['r2']:6.3f} {gz['r2']:7.3f}")

    for f in cv["folds"]:
        lines.append(row(str(f["fold"]), ",".join(_short(t) for t in f["test_trials"])[:22], f, f["n_test"]))
    lines.append("-" * len(head))
    lines.append(row("overall", "pooled over folds", cv["overall"], cv["overall"]["classifier"]["n"]))
    conf = np.array(cv["overall"]["classifier"]["confusion"])
    lines.append("\npooled confusion matrix (rows true, columns predicted): " + ", ".join(class_names))
    w = max(len(c) for c in class_names)
    for name, r in zip(class_names, conf):
        lines.append(f"  {name:>{w}} " + " ".join(f"{v:8d}" for v in r))
    if cv.get("per_trial"):
        lines.append("\nper held-out trial: balanced accuracy | acc RMSE (zero) R² | mag RMSE (zero) R²")
        for name in sorted(cv["per_trial"]):
            p = cv["per_trial"][name]
            lines.append(f"  {name[:40]:40s} {p['balanced_accuracy']:6.3f} | {p['acc_rmse']:6.3f} ({p['acc_rmse_zero']:6.3f}) "
                         f"{p['acc_r2']:7.3f} | {p['mag_rmse']:6.3f} ({p['mag_rmse_zero']:6.3f}) {p['mag_r2']:7.3f}")
    lines.append("acc/mag: RMSE [m/s², µT] pooled over axes; R² = 1 − SSE/SST; (zero) = predicting no noise; "
                 "(maj) = majority class of the fold's training set")
    return "\n".join(lines)


def _importances(clf, regs, schema) -> str:
    table = _gain_table(clf, regs, schema)
    lines = ["feature," + ",".join(table)]
    for n in feature_ranking(clf, regs, schema):
        lines.append(n + "," + ",".join(f"{table[c][n]:.6f}" for c in table))
    return "\n".join(lines) + "\n"


def _versions() -> dict:
    import scipy
    import sklearn
    import xgboost

    return {"python": platform.python_version(), "togglecf": __version__, "numpy": np.__version__,
            "scipy": scipy.__version__, "xgboost": xgboost.__version__, "scikit-learn": sklearn.__version__}


def run_training(config=None, data_dir=None, trials=None, out=None, cv: bool = True, verbose: bool = True,
                 dataset: WindowData | None = None, backend=None) -> dict:
    """The whole pipeline. Returns a dict with ``metadata``, ``cv``, ``out`` and ``timing``.

    ``dataset``: a ``build_dataset`` result that holds (at least) the selected trials, built with
    this config's label and feature settings, reused instead of rebuilt (sweeps over model
    settings build it once).

    ``backend``: a ``togglecf.backend.Backend`` for the per-trial features and the CV folds; default
    from ``[run] backend/scheduler/retries``: ``local`` runs them in this process (as always),
    ``dask`` on the cluster. With ``[run] distributed_fit = true`` on Dask, the final models are
    trained with ``xgboost.dask`` on the training rows spread over the workers (``togglecf.dask_fit``)."""
    with _train_backend(config, backend) as be:
        return _run_training(config, data_dir, trials, out, cv, verbose, dataset, be)


class _train_backend:
    """The given backend (left open) or one from the config's ``[run]`` (closed afterwards)."""

    def __init__(self, config, backend):
        self.backend, self.own = backend, backend is None
        if backend is None:
            from .backend import InlineBackend, make_backend

            run = load_config(config)["run"]
            self.backend = (make_backend("dask", run["scheduler"], retries=int(run["retries"]))
                            if run["backend"] == "dask" else InlineBackend())

    def __enter__(self):
        return self.backend

    def __exit__(self, *exc):
        if self.own:
            self.backend.close()


def _run_training(config, data_dir, trials, out, cv, verbose, dataset, backend) -> dict:
    t_start = time.perf_counter()
    cfg = load_config(config)
    run = cfg["run"]
    index = DatasetIndex.from_dir(resolve_data_dir(data_dir))
    spec = trials if trials is not None else (None if run["trials"] in ("all", "", None) else run["trials"])
    names = index.select(spec)
    if len(names) < 2:
        raise ValueError(f"training needs at least 2 trials, got {names}")
    label_settings = LabelSettings.from_dict({**cfg["labels"], "seed": run["seed"]})
    feature_settings = FeatureSettings.from_dict(cfg["features"])
    schema = feature_schema(feature_settings)
    class_names = state_names(label_settings.label_set)
    out_dir = Path(out) if out else Path("models") / run["name"]
    timing = {}

    def log(msg):
        if verbose:
            print(msg, file=sys.stderr, flush=True)

    log(f"togglecf train: {len(names)} trials from {index.root} -> {out_dir}"
        + (f" on {backend.describe()}" if backend.name == "dask" else ""))
    t0 = time.perf_counter()
    if dataset is not None:
        if dataset.settings != _dataset_settings(label_settings, feature_settings, label_settings.ransac):
            raise ValueError("run_training: the given dataset was built with other label/feature/RANSAC settings "
                             "than this config's")
        data = dataset.subset(names)
    else:
        data = build_dataset(index, names, label_settings, feature_settings, ransac=label_settings.ransac,
                             backend=backend)
    timing["dataset_s"] = time.perf_counter() - t0
    log(f"{len(data.end)} windows x {data.X.shape[1]} features ({data.train_mask.sum()} training rows) "
        f"in {timing['dataset_s']:.1f} s")
    log("RANSAC inlier fraction per trial (" + ("applied" if label_settings.ransac else "not applied") + "): "
        + ", ".join(f"{_short(n)} {p['inlier_fraction']:.4f}" for n, p in data.per_trial.items()))
    result = {"out": str(out_dir), "timing": timing}
    oof = None
    if cv:
        t0 = time.perf_counter()
        result["cv"], oof = cross_validate(cfg, data, schema, class_names, backend=backend)
        timing["cv_s"] = time.perf_counter() - t0
        if verbose:
            print(format_cv_table(result["cv"], class_names))
    t0 = time.perf_counter()
    rows = np.flatnonzero(data.train_mask)
    if run["distributed_fit"]:
        from .dask_fit import fit_models_dask

        clf, regs = fit_models_dask(backend, cfg, data, rows, schema, class_names)
    else:
        clf, regs = _fit_all(cfg, data, rows, schema, class_names)
    timing["final_fit_s"] = time.perf_counter() - t0
    timing["total_s"] = time.perf_counter() - t_start
    metadata = {
        "run_name": run["name"], "created_by": "togglecf train", "seed": run["seed"],
        "sampling_rate": data.fs, "window": {"window_s": feature_settings.window_s, "hop_s": feature_settings.hop_s,
                                             "window_samples": data.window_samples,
                                             "hop_samples": int(max(1, round(feature_settings.hop_s * data.fs)))},
        "label_settings": label_settings.to_dict(), "ransac": label_settings.ransac,
        "training_trials": names, "n_training_windows": int(len(rows)), "data_dir": str(index.root),
        "data_files": {n: {"file": p["file"], "sha256": p["sha256"]} for n, p in data.per_trial.items()},
        "per_trial": {n: {k: v for k, v in p.items() if k not in ("file", "sha256")} for n, p in data.per_trial.items()},
        "config": cfg, "cv": result.get("cv"), "timing": timing, "versions": _versions(),
    }
    save_bundle(out_dir, clf, regs, metadata)
    atomic_write_text(out_dir / "feature_importances.csv", _importances(clf, regs, schema))
    if cv:
        atomic_write_text(out_dir / "cv_table.txt", format_cv_table(result["cv"], class_names) + "\n")
    gcfg = cfg["gains"]
    if gcfg.get("learn", True):  # the toggling filter's gains, on the same training trials
        from .gains import GainSearch, learn_and_save_gains

        t0 = time.perf_counter()
        search = GainSearch.from_dict({k: v for k, v in gcfg.items() if k not in _GAIN_KEYS})
        preds = None
        if oof is not None:  # every trial's predictions from the CV models that did not train on it
            preds = [hold_predictions(*oof[n], data.per_trial[n]["n_samples"]) for n in names]
            result["oof_predictions"] = dict(zip(names, preds))
        learn_and_save_gains(out_dir, [index.load(n) for n in names], search, tuple(gcfg.get("modes", ("9d", "6d"))),
                             jobs=int(run["nthread"]), log=log, predictions=preds)
        timing["gains_s"] = time.perf_counter() - t0
    timing["total_s"] = time.perf_counter() - t_start
    log(f"wrote {out_dir}/ in {timing['total_s']:.1f} s total (dataset {timing['dataset_s']:.1f} s, "
        f"CV {timing.get('cv_s', 0.0):.1f} s, final fit {timing['final_fit_s']:.1f} s)")
    result["metadata"] = metadata
    result["data"] = data
    return result


def add_train_parser(subparsers):
    """Register ``togglecf train`` on an argparse subparsers object."""
    sp = subparsers.add_parser("train", help="learn the motion-state classifier and noise regressors "
                               "(CV by trial, then a final fit) and save them under models/NAME")
    sp.add_argument("--config", default=str(DEFAULT_CONFIG), metavar="TOML",
                    help="pipeline settings (default: pipelines/configs/default.toml)")
    sp.add_argument("--data", metavar="DIR", help="BROAD directory (default: $TOGGLECF_DATA, else "
                    "../shared/data/broad next to the repo, else ./data/broad)")
    sp.add_argument("--trials", metavar="LIST", help="comma-separated trial numbers or names (default: config)")
    sp.add_argument("--out", metavar="DIR", help="model directory (default: models/<run.name>)")
    sp.add_argument("--no-cv", dest="cv", action="store_false", help="skip cross-validation (final fit only)")
    from .backend import add_backend_args

    add_backend_args(sp)
    sp.add_argument("--distributed-fit", action="store_true", default=None,
                    help="with --backend dask: train the final models with xgboost.dask on the workers "
                    "(also [run] distributed_fit)")
    sp.set_defaults(func=cmd_train)
    return sp


def cmd_train(args):
    cfg = load_config(args.config)
    from .backend import backend_settings

    cfg["run"].update({k: v for k, v in backend_settings(args, cfg["run"]).items() if k in cfg["run"]})
    if getattr(args, "distributed_fit", None):
        cfg["run"]["distributed_fit"] = True
    run_training(cfg, data_dir=args.data, trials=args.trials, out=args.out, cv=args.cv)
    return 0
