"""The learning code: labels and RANSAC-cleaned targets, the training windows, XGBoost estimators,
cross-validation by trial, the fold protocols and the flat forest the filter loop walks."""
from togglecf.learn.compiled import CompiledModels, hold_predictions
from togglecf.learn.cv import cross_validate, format_cv_table
from togglecf.learn.dataset import WindowData, build_dataset
from togglecf.learn.fitting import feature_ranking, fit_all, make_models
from togglecf.learn.folds import trial_folds, window_group_folds
from togglecf.learn.labels import LabelSettings, Targets, make_targets, state_names
from togglecf.learn.models import ModelBundle, MotionClassifier, NoiseRegressor, load_bundle, save_bundle
from togglecf.learn.trees import FlatForest

__all__ = ["CompiledModels", "hold_predictions", "cross_validate", "format_cv_table", "WindowData", "build_dataset",
           "feature_ranking", "fit_all", "make_models", "trial_folds", "window_group_folds", "LabelSettings",
           "Targets", "make_targets", "state_names", "ModelBundle", "MotionClassifier", "NoiseRegressor",
           "load_bundle", "save_bundle", "FlatForest"]
