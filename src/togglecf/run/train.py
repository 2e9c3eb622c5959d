"""``togglecf train``: targets -> RANSAC cleaning -> features -> cross-validation by trial -> final
fit -> the toggling gains, all written to one model directory.

The learning steps live in ``togglecf.learn`` (dataset, CV, fitting); the gains in
``togglecf.toggling.gains``. This module runs them in order, logs progress and writes the
artifacts (``learn.models.save_bundle``, ``gains.json``, ``cv_table.txt``,
``feature_importances.csv``).
"""
from __future__ import annotations

import logging
import platform
import time
from pathlib import Path
from typing import NamedTuple

import numpy as np
import scipy

from togglecf import __version__
from togglecf.core.extras import deferred
from togglecf.core.io import atomic_write_text
from togglecf.data.broad import open_index, short_trial_name
from togglecf.features.windows import FeatureSettings, feature_schema
from togglecf.learn.compiled import CompiledModels, hold_predictions
from togglecf.learn.cv import cross_validate, format_cv_table
from togglecf.learn.dask_fit import fit_models_dask
from togglecf.learn.dataset import WindowData, build_dataset, dataset_settings
from togglecf.learn.fitting import fit_all, importances_csv
from togglecf.learn.labels import LabelSettings, state_names
from togglecf.learn.models import save_bundle
from togglecf.learn.ranges import feature_ranges
from togglecf.parallel.backend import InlineBackend, make_backend
from togglecf.run.config import GAIN_KEYS, load_config
from togglecf.toggling.gains import GAINS_FILE, GainSearch, VQFGainSearch, learn_and_save_gains

sklearn = deferred("sklearn", extra="train", what="togglecf training (togglecf.run.train)")
xgboost = deferred("xgboost", extra="train", what="togglecf training (togglecf.run.train)")

__all__ = ["TrainedModels", "run_training"]

log = logging.getLogger(__name__)


def _versions() -> dict:
    return {"python": platform.python_version(), "togglecf": __version__, "numpy": np.__version__,
            "scipy": scipy.__version__, "xgboost": xgboost.__version__, "scikit-learn": sklearn.__version__}


class TrainedModels(NamedTuple):
    """What a training wrote to its model directory, in memory (as that directory reads back)."""

    models: CompiledModels  # the filter's flat forest, its feature settings and training ranges
    gains: dict  # mode (``gains.MODES``) -> ``gains.LearnedGains`` of the modes learned (empty: none)


def run_training(config=None, data_dir=None, trials=None, out=None, cv: bool = True, verbose: bool = True,
                 dataset: WindowData | None = None, backend=None) -> dict:
    """The whole pipeline. Returns a dict with ``metadata``, ``cv``, ``out``, ``timing`` and ``trained``
    (a ``TrainedModels``: the models and gains written to ``out``, for callers that go on with them).

    ``dataset``: a ``build_dataset`` result that holds (at least) the selected trials, built with
    this config's label and feature settings, reused instead of rebuilt (sweeps over model
    settings build it once).

    ``backend``: a ``togglecf.parallel.backend.Backend`` for the per-trial features and the CV folds; default
    from ``[run] backend/scheduler/retries``: ``local`` runs them in this process (as always),
    ``dask`` on the cluster. With ``[run] distributed_fit = true`` on Dask, the final models are
    trained with ``xgboost.dask`` on the training rows spread over the workers (``togglecf.learn.dask_fit``)."""
    with _train_backend(config, backend) as be:
        return _run_training(config, data_dir, trials, out, cv, verbose, dataset, be)


class _train_backend:
    """The given backend (left open) or one from the config's ``[run]`` (closed afterwards)."""

    def __init__(self, config, backend):
        self.backend, self.own = backend, backend is None
        if backend is None:
            run = load_config(config)["run"]
            self.backend = (make_backend("dask", run["scheduler"], retries=int(run["retries"]))
                            if run["backend"] == "dask" else InlineBackend())

    def __enter__(self):
        return self.backend

    def __exit__(self, *exc):
        if self.own:
            self.backend.close()


def _training_data(index, names, label_settings, feature_settings, dataset, backend):
    """The windows, features and targets of ``names``: a subset of the given ``dataset`` (built once
    for several trainings, with the same settings), else built here."""
    if dataset is None:
        return build_dataset(index, names, label_settings, feature_settings, ransac=label_settings.ransac,
                             backend=backend)
    if dataset.settings != dataset_settings(label_settings, feature_settings, label_settings.ransac):
        raise ValueError("run_training: the given dataset was built with other label/feature/RANSAC settings "
                         "than this config's")
    return dataset.subset(names)


def _learn_gains(cfg: dict, out_dir: Path, trials: list, predictions, say, models: CompiledModels) -> dict:
    """The gains of every mode of ``cfg["gains"]`` on the training ``trials`` (their out-of-fold
    ``predictions``, else the final ``models``' own), into ``out_dir/gains.json``; mode -> ``LearnedGains``."""
    gcfg = cfg["gains"]
    search = GainSearch.from_dict({k: v for k, v in gcfg.items() if k not in GAIN_KEYS})
    return learn_and_save_gains(out_dir, trials, search, tuple(gcfg.get("modes", ("9d", "6d"))),
                                jobs=int(cfg["run"]["nthread"]), log=say, predictions=predictions,
                                vqf_search=VQFGainSearch.from_dict(gcfg.get("vqf", {})), models=models)


def _data_dir_meta(index):
    """``data_dir`` of the metadata: the directory, or the list of them (trial names ``<dataset>/<trial>``)."""
    root = index.root
    return [str(r) for r in root] if isinstance(root, (tuple, list)) else str(root)


def _write_models(out_dir: Path, clf, regs: dict, metadata: dict, schema, cv, class_names) -> CompiledModels:
    """The fitted models, their importances and the CV table (``cv``: ``None`` without CV) into ``out_dir``
    (an earlier ``gains.json`` removed); returns the models as the directory reads back
    (``CompiledModels.stored``), flattened once."""
    models = CompiledModels.from_fitted(clf, regs, metadata)
    # an earlier run's gains.json belongs to its models: removed, so that none of its modes survives beside
    # these (``save_gains`` adds each mode of this run to the file) and a damaged one cannot stop the run
    (out_dir / GAINS_FILE).unlink(missing_ok=True)
    save_bundle(out_dir, clf, regs, metadata, forest=models.forest)
    atomic_write_text(out_dir / "feature_importances.csv", importances_csv(clf, regs, schema))
    if cv is not None:
        atomic_write_text(out_dir / "cv_table.txt", format_cv_table(cv, class_names) + "\n")
    return models


def _run_training(config, data_dir, trials, out, cv, verbose, dataset, backend) -> dict:
    t_start = time.perf_counter()
    cfg = load_config(config)
    run = cfg["run"]
    index = open_index(data_dir if data_dir else (run["data"] or None))  # --data > [run] data > default
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

    def say(msg):  # progress: to the log (stderr), unless quiet
        if verbose:
            log.info(msg)

    roots = _data_dir_meta(index)
    say(f"togglecf train: {len(names)} trials from {', '.join(roots) if isinstance(roots, list) else roots} -> {out_dir}"
        + (f" on {backend.describe()}" if backend.name == "dask" else ""))
    t0 = time.perf_counter()
    data = _training_data(index, names, label_settings, feature_settings, dataset, backend)
    timing["dataset_s"] = time.perf_counter() - t0
    say(f"{len(data.end)} windows x {data.X.shape[1]} features ({data.train_mask.sum()} training rows) "
        f"in {timing['dataset_s']:.1f} s")
    say("RANSAC inlier fraction per trial (" + ("applied" if label_settings.ransac else "not applied") + "): "
        + ", ".join(f"{short_trial_name(n)} {p['inlier_fraction']:.4f}" for n, p in data.per_trial.items()))
    result = {"out": str(out_dir), "timing": timing}
    oof = None
    if cv:
        t0 = time.perf_counter()
        result["cv"], oof = cross_validate(cfg, data, schema, class_names, backend=backend)
        # every trial's per-sample predictions from the CV models that did not train on it
        result["oof_predictions"] = {n: hold_predictions(*oof[n], data.per_trial[n]["n_samples"]) for n in names}
        timing["cv_s"] = time.perf_counter() - t0
        if verbose:
            print(format_cv_table(result["cv"], class_names))
    t0 = time.perf_counter()
    rows = np.flatnonzero(data.train_mask)
    if run["distributed_fit"]:
        clf, regs = fit_models_dask(backend, cfg, data, rows, schema, class_names)
    else:
        clf, regs = fit_all(cfg, data, rows, schema, class_names)
    timing["final_fit_s"] = time.perf_counter() - t0
    timing["total_s"] = time.perf_counter() - t_start
    metadata = {
        "run_name": run["name"], "created_by": "togglecf train", "seed": run["seed"],
        # the training trials' common rate [Hz] (None when they differ); the models and the gains in gains.json
        # are in seconds, so they apply at any rate
        "sampling_rate": data.fs,
        "sampling_rates": sorted({round(float(p.get("fs", data.fs)), 6) for p in data.per_trial.values()}),
        "window": {"window_s": feature_settings.window_s, "hop_s": feature_settings.hop_s,
                   "window_samples": data.window_samples,
                   "hop_samples": None if data.fs is None else int(max(1, round(feature_settings.hop_s * data.fs)))},
        # every window of the training trials (the filter meets all of them, not only the valid RANSAC inliers)
        "feature_ranges": feature_ranges(data.X, schema.names, run["max_out_of_range"]),
        "label_settings": label_settings.to_dict(), "ransac": label_settings.ransac,
        "training_trials": names, "n_training_windows": int(len(rows)), "data_dir": _data_dir_meta(index),
        "data_files": {n: {"file": p["file"], "sha256": p["sha256"]} for n, p in data.per_trial.items()},
        "per_trial": {n: {k: v for k, v in p.items() if k not in ("file", "sha256")} for n, p in data.per_trial.items()},
        "config": cfg, "cv": result.get("cv"), "timing": timing, "versions": _versions(),
    }
    models = _write_models(out_dir, clf, regs, metadata, schema, result.get("cv"), class_names)
    gains = {}
    if cfg["gains"].get("learn", True):  # the toggling filter's gains, on the same training trials
        t0 = time.perf_counter()
        gains = _learn_gains(cfg, out_dir, [index.load(n) for n in names],
                             [result["oof_predictions"][n] for n in names] if oof is not None else None, say, models)
        timing["gains_s"] = time.perf_counter() - t0
    timing["total_s"] = time.perf_counter() - t_start
    say(f"wrote {out_dir}/ in {timing['total_s']:.1f} s total (dataset {timing['dataset_s']:.1f} s, "
        f"CV {timing.get('cv_s', 0.0):.1f} s, final fit {timing['final_fit_s']:.1f} s)")
    result["metadata"] = metadata
    result["data"] = data
    result["trained"] = TrainedModels(models, gains)
    return result


