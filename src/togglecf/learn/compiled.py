"""A trained model bundle flattened for the filter loop, and predictions held between hops.

``togglecf train`` stores the flat forest beside the XGBoost files (``INLOOP_FILE``, JSON, its sha256
in ``metadata.json`` ``inloop_forest``): ``CompiledModels.stored`` reads a model directory's filter
models with numpy alone, no XGBoost (``pip install togglecf`` without extras runs trained filters)."""
from __future__ import annotations

import hashlib
import json
from pathlib import Path

import numpy as np

from togglecf.features.windows import (FEATURE_VERSION, FeatureSchema, FeatureSettings, SchemaMismatchError,
                                       compute_features, feature_schema, window_length)
from togglecf.filters.prediction import PredictionLayout
from togglecf.learn.ranges import range_arrays, windows_out_of_range
from togglecf.learn.trees import FlatForest, softmax

__all__ = ["CompiledModels", "hold_predictions", "inloop_forest", "inloop_forest_bytes", "INLOOP_FILE",
           "INLOOP_FORMAT"]

#: the flat forest of a model directory, written by ``learn.models.save_bundle``
INLOOP_FILE = "inloop_forest.json"
#: its layout: ``{"format", "feature_schema_hash", "classes", "forest": FlatForest.to_dict()}``
INLOOP_FORMAT = 1


def inloop_forest(classifier, regressors) -> FlatForest:
    """Fitted models (``learn.models``) as the one flat forest the filter loop walks: outputs = class
    margins, then η̂_a x/y/z, then η̂_m x/y/z. Reads the boosters (XGBoost)."""
    forests = [FlatForest.from_booster(classifier.booster_)]
    for target in ("acc", "mag"):
        forests += [FlatForest.from_booster(b) for b in regressors[target].boosters_]
    return FlatForest.concatenate(forests)


def inloop_forest_bytes(classifier, regressors, forest: FlatForest | None = None) -> bytes:
    """The content of ``INLOOP_FILE`` for fitted models (the same models, the same bytes); ``forest``: their
    ``inloop_forest`` when already flattened."""
    forest = forest if forest is not None else inloop_forest(classifier, regressors)
    doc = {"format": INLOOP_FORMAT, "feature_schema_hash": classifier.schema_.hash,
           "classes": list(classifier.class_names_), "forest": forest.to_dict()}
    return json.dumps(doc, separators=(",", ":")).encode()


class CompiledModels:
    """A trained model bundle as one flat forest: outputs = class margins (softmax applied in the
    loop), then η̂_a x/y/z, then η̂_m x/y/z; plus the feature settings it was trained with and the
    features' training ranges (``feature_low``, ``feature_high`` ``(F,)``, NaN: unbounded) with the
    fallback threshold ``max_out_of_range`` (``learn.ranges``: a window out of range gets a NaN
    prediction row)."""

    def __init__(self, forest: FlatForest, class_names, feature_settings, schema_hash: str, feature_low=None,
                 feature_high=None, max_out_of_range: float = 1.0):
        self.forest = forest
        nan = np.full(forest.n_features, np.nan)
        self.feature_low = nan.copy() if feature_low is None else np.asarray(feature_low, np.float64)
        self.feature_high = nan.copy() if feature_high is None else np.asarray(feature_high, np.float64)
        self.max_out_of_range = float(max_out_of_range)
        if self.feature_low.shape != (forest.n_features,) or self.feature_high.shape != (forest.n_features,):
            raise ValueError(f"feature ranges must have shape ({forest.n_features},)")
        self.class_names = tuple(class_names)
        self.feature_settings = feature_settings
        self.schema_hash = schema_hash
        # the class in which the gyro bias is learned: the model's rest class
        self.static_state = next((c for c in ("rest", "static") if c in self.class_names), self.class_names[0])
        self.layout = PredictionLayout.of(len(self.class_names))
        if forest.n_outputs != self.layout.size:
            raise ValueError(f"forest has {forest.n_outputs} outputs, expected {self.layout.size}: "
                             f"{len(self.class_names)} class probabilities, η̂_a and η̂_m (filters.prediction)")

    @classmethod
    def from_bundle(cls, bundle) -> "CompiledModels":
        """A loaded model bundle (``learn.models.load_bundle``), its boosters flattened (XGBoost)."""
        where = bundle.path or "model bundle"
        settings, ranges = _settings_and_ranges(bundle.schema, bundle.metadata, where)
        return cls(inloop_forest(bundle.classifier, bundle.regressors), bundle.classifier.class_names_, settings,
                   bundle.schema.hash, *ranges)

    @classmethod
    def from_fitted(cls, classifier, regressors, metadata: dict, forest: FlatForest | None = None) -> "CompiledModels":
        """Fitted models (``learn.models``) in memory with the ``metadata`` ``learn.models.save_bundle``
        writes for them (its ``feature_ranges``): the models ``stored`` reads back from their directory,
        array for array. ``forest``: their ``inloop_forest`` when already flattened (XGBoost otherwise)."""
        settings, ranges = _settings_and_ranges(classifier.schema_, metadata, "fitted models")
        forest = forest if forest is not None else inloop_forest(classifier, regressors)
        return cls(forest, classifier.class_names_, settings, classifier.schema_.hash, *ranges)

    @classmethod
    def stored(cls, model_dir) -> "CompiledModels | None":
        """The models of a model directory read from its ``INLOOP_FILE`` with numpy alone (no XGBoost),
        checked as ``from_bundle`` checks them; ``None`` when the directory has none (trained before
        the file was written: ``from_bundle(load_bundle(model_dir))`` flattens its boosters)."""
        d = Path(model_dir)
        meta_path = d / "metadata.json"
        if not meta_path.is_file():
            raise FileNotFoundError(f"{d}: no metadata.json (not a togglecf model directory, or an unfinished run)")
        meta = json.loads(meta_path.read_text())
        entry = meta.get("inloop_forest")
        if not entry:
            return None
        schema = FeatureSchema.from_dict(meta["feature_schema"])
        settings, ranges = _settings_and_ranges(schema, meta, d)
        path = d / entry["file"]
        raw = path.read_bytes()
        if hashlib.sha256(raw).hexdigest() != entry["sha256"]:
            raise ValueError(f"{path}: sha256 differs from metadata.json (file changed or damaged)")
        doc = json.loads(raw)
        if doc.get("format") != INLOOP_FORMAT:
            raise ValueError(f"{path}: format {doc.get('format')!r}, this togglecf reads format {INLOOP_FORMAT}: "
                             "retrain it with `togglecf train`")
        forest = FlatForest.from_dict(doc["forest"])
        if (doc["feature_schema_hash"] != schema.hash or list(doc["classes"]) != list(meta["classes"])
                or forest.n_features != len(schema.names)):
            raise SchemaMismatchError(f"{path}: made for other models than {meta_path} describes (feature schema "
                                      "or classes differ)")
        return cls(forest, meta["classes"], settings, schema.hash, *ranges)

    def predict_samples(self, gyr, acc, mag, fs: float) -> np.ndarray:
        """Per-sample predictions ``(N, S + 6)`` as the in-loop filter holds them: from the
        vectorised features at each window end, held until the next one; NaN before the
        first full window. For learning gains on whole trials without re-running the trees."""
        n = np.shape(gyr)[0]
        if n < window_length(fs, self.feature_settings.window_s):
            return np.full((n, self.forest.n_outputs), np.nan)
        X, ends = compute_features(gyr, acc, mag, fs, self.feature_settings)
        return hold_predictions(ends, self.predict_windows(X), n)

    def predict_windows(self, X) -> np.ndarray:
        """Prediction rows ``(n, S + 6)`` (class probabilities, η̂_a, η̂_m) of feature rows ``X``;
        NaN rows for the windows out of the training range (``out_of_range``)."""
        m = self.forest.predict_margin(X)
        p = self.layout.probabilities
        m[:, p] = softmax(m[:, p])
        m[self.out_of_range(X)] = np.nan
        return m

    def out_of_range(self, X) -> np.ndarray:
        """Bool ``(n,)``: the feature rows ``X`` the fallback rule (``learn.ranges``) refuses."""
        return windows_out_of_range(X, self.feature_low, self.feature_high, self.max_out_of_range)


def _settings_and_ranges(schema: FeatureSchema, metadata: dict, where) -> tuple:
    """The feature settings of trained models (refused when this togglecf computes other features) and
    their training ranges ``(low, high, max_out_of_range)`` (refused when they were not stored)."""
    if schema.version != FEATURE_VERSION:  # other feature definitions: no setting recomputes them
        raise SchemaMismatchError(f"{where}: trained on feature schema v{schema.version}, this togglecf "
                                  f"computes v{FEATURE_VERSION} (togglecf.features.windows): retrain it with "
                                  "`togglecf train`")
    settings = FeatureSettings.from_dict({k: v for k, v in schema.settings.items() if k != "gravity"})
    schema.check(feature_schema(settings), str(where))  # same definitions as training
    if "feature_ranges" not in metadata:  # bundle_format < 3: the fallback would silently be off
        raise ValueError(f"{where}: trained without feature ranges "
                         f"(bundle_format {metadata.get('bundle_format')}; the out-of-range fallback needs "
                         "format 3): retrain it with `togglecf train`")
    return settings, range_arrays(metadata["feature_ranges"], schema.names)


def hold_predictions(ends, values, n: int) -> np.ndarray:
    """Per-sample predictions ``(n, k)``: the row of the last window end ``<= sample`` (as the
    in-loop filter holds them between hops); NaN before the first window end."""
    ends = np.asarray(ends)
    order = np.argsort(ends, kind="stable")
    ends, values = ends[order], np.asarray(values)[order]
    pred = np.full((n, values.shape[1]), np.nan)
    idx = np.searchsorted(ends, np.arange(n), side="right") - 1
    pred[idx >= 0] = values[idx[idx >= 0]]
    return pred
