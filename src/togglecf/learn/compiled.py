"""A trained model bundle flattened for the filter loop, and predictions held between hops."""
from __future__ import annotations

import numpy as np

from togglecf.features.windows import (FEATURE_VERSION, FeatureSettings, SchemaMismatchError, compute_features,
                                       feature_schema, window_length)
from togglecf.filters.toggling import N_PRED_NOISE
from togglecf.learn.ranges import range_arrays, windows_out_of_range
from togglecf.learn.trees import FlatForest, softmax

__all__ = ["CompiledModels", "hold_predictions"]


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
        if forest.n_outputs != len(self.class_names) + N_PRED_NOISE:
            raise ValueError(f"forest has {forest.n_outputs} outputs, expected {len(self.class_names)} classes + 6")

    @classmethod
    def from_bundle(cls, bundle) -> "CompiledModels":
        where = bundle.path or "model bundle"
        if bundle.schema.version != FEATURE_VERSION:  # other feature definitions: no setting recomputes them
            raise SchemaMismatchError(f"{where}: trained on feature schema v{bundle.schema.version}, this togglecf "
                                      f"computes v{FEATURE_VERSION} (togglecf.features.windows): retrain it with "
                                      "`togglecf train`")
        settings = FeatureSettings.from_dict({k: v for k, v in bundle.schema.settings.items() if k != "gravity"})
        bundle.schema.check(feature_schema(settings), str(where))  # same definitions as training
        forests = [FlatForest.from_booster(bundle.classifier.booster_)]
        for target in ("acc", "mag"):
            forests += [FlatForest.from_booster(b) for b in bundle.regressors[target].boosters_]
        if "feature_ranges" not in bundle.metadata:  # bundle_format < 3: the fallback would silently be off
            raise ValueError(f"{bundle.path or 'model bundle'}: trained without feature ranges "
                             f"(bundle_format {bundle.metadata.get('bundle_format')}; the out-of-range fallback needs "
                             "format 3): retrain it with `togglecf train`")
        low, high, max_out = range_arrays(bundle.metadata["feature_ranges"], bundle.schema.names)
        return cls(FlatForest.concatenate(forests), bundle.classifier.class_names_, settings, bundle.schema.hash,
                   low, high, max_out)

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
        k = len(self.class_names)
        m[:, :k] = softmax(m[:, :k])
        m[self.out_of_range(X)] = np.nan
        return m

    def out_of_range(self, X) -> np.ndarray:
        """Bool ``(n,)``: the feature rows ``X`` the fallback rule (``learn.ranges``) refuses."""
        return windows_out_of_range(X, self.feature_low, self.feature_high, self.max_out_of_range)


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
