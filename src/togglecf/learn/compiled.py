"""A trained model bundle flattened for the filter loop, and predictions held between hops."""
from __future__ import annotations

import numpy as np

from togglecf.features.windows import FeatureSettings, compute_features, feature_schema, window_length
from togglecf.filters.toggling import N_PRED_NOISE
from togglecf.learn.trees import FlatForest, softmax

__all__ = ["CompiledModels", "hold_predictions"]


class CompiledModels:
    """A trained model bundle as one flat forest: outputs = class margins (softmax applied in the
    loop), then η̂_a x/y/z, then η̂_m x/y/z; plus the feature settings it was trained with."""

    def __init__(self, forest: FlatForest, class_names, feature_settings, schema_hash: str):
        self.forest = forest
        self.class_names = tuple(class_names)
        self.feature_settings = feature_settings
        self.schema_hash = schema_hash
        # the class in which the gyro bias is learned: the model's rest class
        self.static_state = next((c for c in ("rest", "static") if c in self.class_names), self.class_names[0])
        if forest.n_outputs != len(self.class_names) + N_PRED_NOISE:
            raise ValueError(f"forest has {forest.n_outputs} outputs, expected {len(self.class_names)} classes + 6")

    @classmethod
    def from_bundle(cls, bundle) -> "CompiledModels":
        settings = FeatureSettings.from_dict({k: v for k, v in bundle.schema.settings.items() if k != "gravity"})
        feature_schema(settings).check(bundle.schema, "streaming features")  # same definitions as training
        forests = [FlatForest.from_booster(bundle.classifier.booster_)]
        for target in ("acc", "mag"):
            forests += [FlatForest.from_booster(b) for b in bundle.regressors[target].boosters_]
        return cls(FlatForest.concatenate(forests), bundle.classifier.class_names_, settings, bundle.schema.hash)

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
        """Prediction rows ``(n, S + 6)`` (class probabilities, η̂_a, η̂_m) of feature rows ``X``."""
        m = self.forest.predict_margin(X)
        k = len(self.class_names)
        m[:, :k] = softmax(m[:, :k])
        return m


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
