"""Causal-window features of the IMU signals: the vectorised definition (``windows``) and the
streaming one the filter loop and the C filter compute sample by sample (``streaming``)."""
from togglecf.features.streaming import StreamingFeatures
from togglecf.features.windows import (
                                       FEATURE_VERSION,
                                       FeatureSchema,
                                       FeatureSettings,
                                       SchemaMismatchError,
                                       compute_features,
                                       feature_schema,
                                       hop_length,
                                       trial_features,
                                       window_length,
)

__all__ = ["StreamingFeatures", "FEATURE_VERSION", "FeatureSchema", "FeatureSettings", "SchemaMismatchError",
           "compute_features", "feature_schema", "hop_length", "trial_features", "window_length"]
