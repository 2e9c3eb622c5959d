"""Flattened XGBoost trees in numba equal xgboost's own predictions (margins and probabilities),
including missing values and thresholds that sit exactly on float32 feature values."""
import numpy as np
import pytest
import xgboost as xgb

from togglecf.learn.trees import COMPLETE_MAX_DEPTH, FlatForest, predict_margin_row_complete

# xgboost sums leaves in float32; we sum in float64: differences are float32 rounding of the
# margin (~1e-7 relative), far below the 1e-5 the export must meet.
ATOL = 2e-6


def data(rng, n=3000, d=6):
    X = rng.standard_normal((n, d)).astype(np.float32)
    X[rng.random((n, d)) < 0.1] = np.nan  # 10 % missing values
    X[:, 5] = np.round(X[:, 5], 1)  # repeated values: thresholds land exactly on data points
    return X


@pytest.mark.parametrize("objective,n_class", [("binary:logistic", 0), ("multi:softprob", 4),
                                               ("reg:squarederror", 0)])
def test_flat_forest_equals_xgboost(rng, objective, n_class):
    X = data(rng)
    signal = np.nan_to_num(X[:, 0]) + 0.5 * np.nan_to_num(X[:, 1]) * np.nan_to_num(X[:, 5])
    if objective == "binary:logistic":
        y = (signal > 0.2).astype(int)
    elif n_class:
        y = np.digitize(signal, [-0.7, 0.0, 0.7])
    else:
        y = 3.0 * signal + 1.0
    params = {"objective": objective, "max_depth": 5, "eta": 0.3, "seed": 0, "nthread": 1}
    if n_class:
        params["num_class"] = n_class
    booster = xgb.train(params, xgb.DMatrix(X, label=y, missing=np.nan), 20)
    forest = FlatForest.from_booster(booster)
    X_test = data(np.random.default_rng(99), 2000)
    dm = xgb.DMatrix(X_test, missing=np.nan)
    margin_ref = booster.predict(dm, output_margin=True).reshape(len(X_test), -1)
    np.testing.assert_allclose(forest.predict_margin(X_test), margin_ref, atol=ATOL, rtol=0)
    np.testing.assert_allclose(forest.predict(X_test), booster.predict(dm), atol=ATOL, rtol=0)
    # float64 input gives the same as float32 input: the comparison is done in float32
    np.testing.assert_array_equal(forest.predict_margin(X_test.astype(np.float64)), forest.predict_margin(X_test))


def test_sklearn_wrapper_and_errors(rng):
    X = data(rng, 500)
    clf = xgb.XGBClassifier(n_estimators=5, max_depth=3, random_state=0, n_jobs=1)
    clf.fit(X, (np.nan_to_num(X[:, 0]) > 0).astype(int))
    forest = FlatForest.from_booster(clf)
    np.testing.assert_allclose(forest.predict(X), clf.predict_proba(X)[:, 1], atol=ATOL)
    with pytest.raises(ValueError, match=r"expected shape \(n, 6\)"):
        forest.predict(X[:, :5])
    bad = xgb.train({"objective": "count:poisson"}, xgb.DMatrix(X, label=np.ones(500)), 2)
    with pytest.raises(ValueError, match="not supported"):
        FlatForest.from_booster(bad)


def test_concatenated_forest_gives_each_models_margins(rng):
    X = data(rng, 1000)
    y = (np.nan_to_num(X[:, 0]) > 0).astype(int) + (np.nan_to_num(X[:, 1]) > 0)
    clf = xgb.train({"objective": "multi:softprob", "num_class": 3, "max_depth": 4, "seed": 0}, xgb.DMatrix(X, label=y), 8)
    reg = xgb.train({"objective": "reg:squarederror", "max_depth": 3, "seed": 0, "base_score": 0.0},
                    xgb.DMatrix(X, label=np.nan_to_num(X[:, 2])), 6)
    a, b = FlatForest.from_booster(clf), FlatForest.from_booster(reg)
    both = FlatForest.concatenate([a, b, b])
    m = both.predict_margin(X)
    assert m.shape == (1000, 5) and both.n_nodes == a.n_nodes + 2 * b.n_nodes
    np.testing.assert_array_equal(m[:, :3], a.predict_margin(X))
    np.testing.assert_array_equal(m[:, 3], b.predict_margin(X)[:, 0])
    np.testing.assert_array_equal(m[:, 4], b.predict_margin(X)[:, 0])
    with pytest.raises(ValueError, match="share their number of features"):
        FlatForest.concatenate([a, FlatForest.from_booster(xgb.train({}, xgb.DMatrix(X[:, :3], label=y), 1))])


def _complete_margins(forest, X):
    cf = forest.complete()
    arrays = cf.arrays()
    out = np.empty((len(X), forest.n_outputs))
    for i in range(len(X)):
        predict_margin_row_complete(X[i], arrays, out[i])
    return out


def test_complete_forest_gives_the_same_margins_bit_for_bit(rng):
    """The padded breadth-first layout walked eight trees at a time (the filter loop's) equals the
    plain walk exactly: missing values, ±inf, trees of mixed and partial depths, a block remainder."""
    X = data(rng, 1000).astype(np.float64)
    y = (np.nan_to_num(X[:, 0]) > 0).astype(int) + (np.nan_to_num(X[:, 1]) > 0)
    clf = xgb.train({"objective": "multi:softprob", "num_class": 3, "max_depth": 5, "seed": 0},
                    xgb.DMatrix(X, label=y, missing=np.nan), 7)
    reg = xgb.train({"objective": "reg:squarederror", "max_depth": 3, "seed": 0, "min_child_weight": 50},
                    xgb.DMatrix(X, label=np.nan_to_num(X[:, 2])), 5)
    X[rng.random(X.shape) < 0.03] = np.inf
    X[rng.random(X.shape) < 0.03] = -np.inf
    both = FlatForest.concatenate([FlatForest.from_booster(clf), FlatForest.from_booster(reg)])
    depths = both.depths()
    assert len(set(depths.tolist())) > 1  # blocks pad trees of different depths
    np.testing.assert_array_equal(_complete_margins(both, X), both.predict_margin(X))
    kept = both.without_outputs([1, 3])  # a subset of the trees (the filter's walked ones), 13 trees: a remainder
    np.testing.assert_array_equal(_complete_margins(kept, X), kept.predict_margin(X))


def test_complete_forest_refuses_what_it_cannot_lay_out(rng):
    X = data(rng, 300)
    reg = xgb.train({"objective": "reg:squarederror", "max_depth": 3, "seed": 0}, xgb.DMatrix(X, label=np.nan_to_num(X[:, 0])), 2)
    f = FlatForest.from_booster(reg)
    inner = np.flatnonzero(f.feature >= 0)
    f.threshold = f.threshold.copy()
    f.threshold[inner[0]] = -np.inf
    with pytest.raises(ValueError, match="-inf"):
        f.complete()
    deep = FlatForest.from_booster(reg)
    deep.depths = lambda: np.full(len(deep.roots), COMPLETE_MAX_DEPTH + 1)
    with pytest.raises(ValueError, match="deeper"):
        deep.complete()
