"""XGBoost models of the learning pipeline: a motion-state classifier and per-axis noise regressors.

Estimators follow scikit-learn's conventions: settings in ``__init__``, learning in ``fit``,
learned attributes end in ``_``. Every model records the ``FeatureSchema`` it was trained on and
refuses (``SchemaMismatchError``) features computed with another schema.

* ``MotionClassifier``: ``multi:softprob`` over ``len(class_names)`` classes (also for the binary
  label set), optional balanced sample weights.
* ``NoiseRegressor``: one ``reg:squarederror`` booster per sensor axis with ``base_score = 0``
  (a later TL2cgen export mishandles per-target base scores), predicting ``η`` ``(n, 3)``.

Settings: ``tree_method = hist``, ``nthread`` (default 2) and a fixed ``seed``, so the same data
give byte-identical model files. Models are saved as UBJSON (``.ubj``), never pickled.

``save_bundle`` / ``load_bundle`` write and read a model directory (see ``models/README.md``):
model files, the flat forest the filter loop walks (``inloop_forest.json``: ``learn.compiled``, read
without XGBoost), ``metadata.json`` (``bundle_format``, schema, settings, the training trials' sampling
rates, file hashes, CV metrics, versions).
"""
from __future__ import annotations

import hashlib
import inspect
import json
import os
import warnings
from pathlib import Path

import numpy as np

from togglecf.core.extras import require
from togglecf.core.io import atomic_write_bytes, atomic_write_json
from togglecf.features.windows import FeatureSchema, SchemaMismatchError
from togglecf.learn.compiled import INLOOP_FILE, inloop_forest_bytes

__all__ = ["MotionClassifier", "NoiseRegressor", "ModelBundle", "save_bundle", "load_bundle",
           "classification_metrics", "regression_metrics", "SchemaMismatchError", "AXES"]

AXES = ("x", "y", "z")
#: ``metadata.json`` ``bundle_format``: 2 adds ``sampling_rates`` (Hz, of the training trials) and
#: goes with ``gains.json`` format 2 (time constants, ``toggling.gains.GAINS_FORMAT``); 1: per-sample gains;
#: 3 adds ``feature_ranges`` (``learn.ranges``: the training range of each feature and the fallback threshold)
BUNDLE_FORMAT = 3

# OpenMP threads that spin while waiting make XGBoost several times slower when the machine's cores
# are shared with other work; sleeping waits avoid that. Only
# effective if set before XGBoost's OpenMP runtime starts, hence at import of this module.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")


def _xgb(what: str = "training or running XGBoost models (togglecf.learn.models)"):
    return require("xgboost", extra="train", what=what)


class _XGBBase:
    """Shared booster settings and schema checks."""

    def __init__(self, n_estimators: int = 200, max_depth: int = 6, learning_rate: float = 0.1,
                 subsample: float = 0.8, colsample_bytree: float = 0.8, min_child_weight: float = 1.0,
                 reg_lambda: float = 1.0, max_bin: int = 256, nthread: int = 2, seed: int = 0):
        self.n_estimators = n_estimators
        self.max_depth = max_depth
        self.learning_rate = learning_rate
        self.subsample = subsample
        self.colsample_bytree = colsample_bytree
        self.min_child_weight = min_child_weight
        self.reg_lambda = reg_lambda
        self.max_bin = max_bin
        self.nthread = nthread
        self.seed = seed

    def get_params(self) -> dict:
        return {k: getattr(self, k) for k in self.param_names()}

    @classmethod
    def param_names(cls):
        names = []
        for klass in reversed(cls.__mro__):
            if "__init__" in vars(klass):
                names += [n for n, p in inspect.signature(klass.__init__).parameters.items()
                          if n != "self" and p.kind not in (p.VAR_KEYWORD, p.VAR_POSITIONAL)]
        return list(dict.fromkeys(names))

    def _xgb_params(self) -> dict:
        return {"tree_method": "hist", "max_depth": int(self.max_depth), "eta": float(self.learning_rate),
                "subsample": float(self.subsample), "colsample_bytree": float(self.colsample_bytree),
                "min_child_weight": float(self.min_child_weight), "lambda": float(self.reg_lambda),
                "max_bin": int(self.max_bin), "nthread": int(self.nthread), "seed": int(self.seed)}

    def _check_X(self, X, schema: FeatureSchema | None):
        if not hasattr(self, "schema_"):
            raise RuntimeError(f"{type(self).__name__} is not fitted")
        if schema is not None:
            self.schema_.check(schema, type(self).__name__)
        X = np.asarray(X, dtype=np.float64)
        if X.ndim != 2 or X.shape[1] != len(self.schema_.names):
            raise SchemaMismatchError(
                f"{type(self).__name__} expects {len(self.schema_.names)} feature columns (schema "
                f"{self.schema_.hash[:12]}), got array of shape {X.shape}")
        return X

    def _dmatrix(self, X, label=None, weight=None):
        xgb = _xgb()
        return xgb.DMatrix(np.asarray(X, np.float32), label=label, weight=weight,
                           feature_names=list(self.schema_.names), nthread=int(self.nthread))

    def _train(self, params, dtrain):
        xgb = _xgb()
        return xgb.train(params, dtrain, num_boost_round=int(self.n_estimators), verbose_eval=False)


class MotionClassifier(_XGBBase):
    """Motion-state classifier; ``class_weight='balanced'`` weights samples by inverse class frequency."""

    def __init__(self, class_weight: str | None = "balanced", **kwargs):
        super().__init__(**kwargs)
        self.class_weight = class_weight

    def fit(self, X, y, schema: FeatureSchema, class_names):
        self.schema_ = schema
        X = self._check_X(X, None)
        y = np.asarray(y, dtype=np.int64)
        k = len(class_names)
        if y.min() < 0 or y.max() >= k:
            raise ValueError(f"labels must lie in [0, {k - 1}]")
        weight = None
        if self.class_weight == "balanced":
            counts = np.bincount(y, minlength=k).astype(float)
            w_class = np.where(counts > 0, len(y) / (np.count_nonzero(counts) * np.maximum(counts, 1)), 0.0)
            weight = w_class[y]
        elif self.class_weight is not None:
            raise ValueError(f"class_weight must be 'balanced' or None, got {self.class_weight!r}")
        params = {**self._xgb_params(), "objective": "multi:softprob", "num_class": k,
                  "eval_metric": "mlogloss"}
        self.booster_ = self._train(params, self._dmatrix(X, y, weight))
        self.class_names_ = tuple(class_names)
        self.classes_ = np.arange(k)
        self.n_features_in_ = X.shape[1]
        return self

    def predict_proba(self, X, schema: FeatureSchema | None = None) -> np.ndarray:
        X = self._check_X(X, schema)
        p = self.booster_.predict(self._dmatrix(X))
        return p.reshape(X.shape[0], len(self.classes_))

    def predict(self, X, schema: FeatureSchema | None = None) -> np.ndarray:
        return np.argmax(self.predict_proba(X, schema), axis=1)

    def model_bytes(self) -> dict:
        return {"classifier.ubj": bytes(self.booster_.save_raw(raw_format="ubj"))}


class NoiseRegressor(_XGBBase):
    """Per-axis regressors for a sensor's noise ``η`` ``(n, 3)`` (``target`` names the sensor)."""

    def __init__(self, target: str = "acc", **kwargs):
        super().__init__(**kwargs)
        self.target = target

    def fit(self, X, Y, schema: FeatureSchema):
        self.schema_ = schema
        X = self._check_X(X, None)
        Y = np.asarray(Y, dtype=np.float64)
        if Y.shape != (X.shape[0], 3) or not np.all(np.isfinite(Y)):
            raise ValueError(f"targets must be finite with shape ({X.shape[0]}, 3), got {Y.shape}")
        params = {**self._xgb_params(), "objective": "reg:squarederror", "base_score": 0.0}
        self.boosters_ = []
        for i in range(3):
            self.boosters_.append(self._train(params, self._dmatrix(X, Y[:, i])))
        self.n_features_in_ = X.shape[1]
        return self

    def predict(self, X, schema: FeatureSchema | None = None) -> np.ndarray:
        X = self._check_X(X, schema)
        d = self._dmatrix(X)
        return np.stack([b.predict(d) for b in self.boosters_], axis=1).astype(np.float64)

    def model_bytes(self) -> dict:
        return {f"{self.target}_{ax}.ubj": bytes(b.save_raw(raw_format="ubj"))
                for ax, b in zip(AXES, self.boosters_)}


# ------------------------------------------------------------------------------------------ bundle

class ModelBundle:
    """A loaded model directory: ``classifier``, ``regressors`` (``{"acc": ..., "mag": ...}``),
    ``schema``, ``metadata``."""

    def __init__(self, classifier, regressors: dict, schema: FeatureSchema, metadata: dict):
        self.classifier = classifier
        self.regressors = regressors
        self.schema = schema
        self.metadata = metadata
        self.path = None  # the directory it was loaded from (``load_bundle``)

    def check_schema(self, schema: FeatureSchema):
        self.schema.check(schema, "model bundle")


def _sha256(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def save_bundle(out_dir, classifier: MotionClassifier, regressors: dict, metadata: dict, forest=None) -> dict:
    """Write the model files and ``metadata.json`` (which records each file's sha256) atomically;
    ``metadata.json`` is written last so a complete bundle is one whose metadata exists. ``forest``: the
    models' ``learn.compiled.inloop_forest`` when already flattened (else flattened here)."""
    out = Path(out_dir)
    files = dict(classifier.model_bytes())
    for reg in regressors.values():
        files.update(reg.model_bytes())
    hashes = {}
    for name, data in files.items():
        atomic_write_bytes(out / name, data)
        hashes[name] = _sha256(data)
    inloop = inloop_forest_bytes(classifier, regressors, forest)  # the filter's trees, read later without XGBoost
    atomic_write_bytes(out / INLOOP_FILE, inloop)
    meta = {"bundle_format": BUNDLE_FORMAT, **metadata, "feature_schema": classifier.schema_.to_dict(),
            "classes": list(classifier.class_names_), "model_files": hashes,
            "inloop_forest": {"file": INLOOP_FILE, "sha256": _sha256(inloop)},
            "classifier_params": classifier.get_params(),
            "regressor_params": {k: r.get_params() for k, r in regressors.items()}}
    atomic_write_json(out / "metadata.json", meta)
    return hashes


def load_bundle(model_dir, expected_schema: FeatureSchema | None = None) -> ModelBundle:
    """Load a model directory, verifying file hashes and (when given) the feature schema.

    Raises ``SchemaMismatchError`` when ``expected_schema`` (the features the caller will feed)
    differs from the schema the models were trained on, ``ValueError`` for a damaged bundle,
    ``MissingExtraError`` without XGBoost (the ``train`` extra; the filter's trees alone:
    ``learn.compiled.CompiledModels.stored``).
    """
    d = Path(model_dir)
    xgb = _xgb(f"reading the XGBoost models of {d}")
    meta_path = d / "metadata.json"
    if not meta_path.is_file():
        raise FileNotFoundError(f"{d}: no metadata.json (not a togglecf model directory, or an unfinished run)")
    meta = json.loads(meta_path.read_text())
    schema = FeatureSchema.from_dict(meta["feature_schema"])
    if expected_schema is not None:
        schema.check(expected_schema, f"model {d}")
    boosters = {}
    for name, digest in meta["model_files"].items():
        data = (d / name).read_bytes()
        if _sha256(data) != digest:
            raise ValueError(f"{d / name}: sha256 differs from metadata.json (file changed or damaged)")
        b = xgb.Booster()
        b.load_model(bytearray(data))
        if b.feature_names is not None and tuple(b.feature_names) != schema.names:
            raise SchemaMismatchError(f"{d / name}: its feature names differ from the bundle's schema")
        boosters[name] = b
    clf = MotionClassifier(**meta["classifier_params"])
    clf.schema_, clf.booster_ = schema, boosters["classifier.ubj"]
    clf.class_names_ = tuple(meta["classes"])
    clf.classes_ = np.arange(len(clf.class_names_))
    clf.n_features_in_ = len(schema.names)
    regs = {}
    for target, params in meta["regressor_params"].items():
        r = NoiseRegressor(**params)
        r.schema_ = schema
        r.boosters_ = [boosters[f"{target}_{ax}.ubj"] for ax in AXES]
        r.n_features_in_ = len(schema.names)
        regs[target] = r
    bundle = ModelBundle(clf, regs, schema, meta)
    bundle.path = d
    return bundle


# ----------------------------------------------------------------------------------------- metrics

def classification_metrics(y_true, proba, n_classes: int) -> dict:
    """Balanced accuracy, macro F1 (over the classes present in ``y_true`` or predicted), macro
    one-vs-rest ROC-AUC (over the classes present in ``y_true`` with both outcomes; for two classes
    the AUC of class 1), confusion matrix (rows true, columns predicted)."""
    metrics = require("sklearn.metrics", extra="train", what="computing classification metrics")
    balanced_accuracy_score, confusion_matrix = metrics.balanced_accuracy_score, metrics.confusion_matrix
    f1_score, roc_auc_score = metrics.f1_score, metrics.roc_auc_score

    y_true = np.asarray(y_true, np.int64)
    proba = np.asarray(proba, float)
    y_pred = np.argmax(proba, axis=1)
    present = np.unique(np.concatenate([y_true, y_pred]))
    with warnings.catch_warnings():  # a predicted class absent from y_true is expected here
        warnings.simplefilter("ignore", UserWarning)
        bal = float(balanced_accuracy_score(y_true, y_pred))
    out = {"n": int(len(y_true)),
           "balanced_accuracy": bal,
           "f1_macro": float(f1_score(y_true, y_pred, labels=present, average="macro", zero_division=0)),
           "confusion": confusion_matrix(y_true, y_pred, labels=np.arange(n_classes)).tolist()}
    aucs = []
    classes = [1] if n_classes == 2 else range(n_classes)
    for c in classes:
        pos = y_true == c
        if 0 < pos.sum() < len(y_true):
            aucs.append(roc_auc_score(pos, proba[:, c]))
    out["roc_auc"] = float(np.mean(aucs)) if aucs else float("nan")
    return out


def regression_metrics(y_true, y_pred) -> dict:
    """RMSE and R² per axis and pooled over the three axes (R² = 1 − SSE/SST, SST around each
    axis's mean)."""
    y_true = np.asarray(y_true, float)
    y_pred = np.asarray(y_pred, float)
    err = y_true - y_pred
    sse = np.sum(err ** 2, axis=0)
    sst = np.sum((y_true - y_true.mean(axis=0)) ** 2, axis=0)
    out = {"n": int(len(y_true)),
           "rmse": float(np.sqrt(np.mean(err ** 2))),
           "r2": float(1.0 - sse.sum() / sst.sum()) if sst.sum() > 0 else float("nan")}
    for i, ax in enumerate(AXES):
        out[f"rmse_{ax}"] = float(np.sqrt(sse[i] / len(y_true)))
        out[f"r2_{ax}"] = float(1.0 - sse[i] / sst[i]) if sst[i] > 0 else float("nan")
    return out
