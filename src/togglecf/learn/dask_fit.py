"""Final models trained with ``xgboost.dask`` on a Dask cluster (``[run] distributed_fit = true``).

The training rows are split into one block per trial, the blocks are placed on the workers, and
``xgboost.dask.train`` builds every booster from the partitions where they lie (XGBoost's
collective: quantile sketches and gradient histograms are merged across the workers each round).

Not bit-identical to single-node XGBoost: the merged quantile sketch gives (slightly) different
histogram cut points, histogram sums are added in another order, and row subsampling draws per
worker. The models are equivalent in quality, not in bits; the test checks agreement with the
single-node models within a stated tolerance. Everything else (the cross-validation folds, which are
single-node XGBoost tasks) is bit-identical to the local backend.
"""
from __future__ import annotations

import numpy as np

from togglecf.core.extras import require
from togglecf.learn.fitting import make_models
from togglecf.parallel.backend import BackendError, DaskBackend

__all__ = ["fit_models_dask", "dask_arrays"]


def dask_arrays(client, blocks, dtype=np.float32):
    """Blocks (list of 2-D numpy arrays with the same columns) scattered to the workers -> one dask array
    whose partitions are those blocks (row-wise)."""
    da = require("dask.array", extra="dask", what="[run] distributed_fit")
    blocks = [np.ascontiguousarray(b, dtype=dtype) for b in blocks if len(b)]
    futs = client.scatter(blocks, hash=False)
    return da.concatenate([da.from_delayed(f, shape=b.shape, dtype=b.dtype) for f, b in zip(futs, blocks)], axis=0)


def fit_models_dask(backend, cfg, data, rows, schema, class_names):
    """Classifier and regressors like ``learn.fitting.fit_models`` on ``rows``, trained with ``xgboost.dask``."""
    if not isinstance(backend, DaskBackend):
        raise BackendError("[run] distributed_fit = true needs --backend dask (and a --scheduler)")
    if int(cfg["run"].get("max_features", 0) or 0) > 0:
        raise ValueError("[run] distributed_fit does not support max_features > 0; use the local final fit")
    dxgb = require("xgboost.dask", extra="dask", what="[run] distributed_fit")

    client = backend.client
    clf, regs = make_models(cfg)
    rows = np.asarray(rows)
    groups = data.group[rows]
    split = [rows[groups == g] for g in np.unique(groups)]  # one block per trial

    def X_blocks():
        return dask_arrays(client, [data.X[r] for r in split])

    def col(values):
        return dask_arrays(client, [values[r].reshape(-1, 1) for r in split], np.float64)[:, 0]

    X = X_blocks()
    names = list(schema.names)
    # classifier: the same balanced weights as MotionClassifier.fit
    y = data.state[rows].astype(np.int64)
    k = len(class_names)
    weight = None
    if clf.class_weight == "balanced":
        counts = np.bincount(y, minlength=k).astype(float)
        w_class = np.where(counts > 0, len(y) / (np.count_nonzero(counts) * np.maximum(counts, 1)), 0.0)
        w_all = np.zeros(len(data.state))
        w_all[rows] = w_class[y]
        weight = col(w_all)
    dtrain = dxgb.DaskDMatrix(client, X, col(data.state.astype(np.float64)), weight=weight, feature_names=names)
    params = {**clf._xgb_params(), "objective": "multi:softprob", "num_class": k, "eval_metric": "mlogloss"}
    clf.booster_ = dxgb.train(client, params, dtrain, num_boost_round=int(clf.n_estimators))["booster"]
    clf.schema_, clf.class_names_, clf.classes_, clf.n_features_in_ = schema, tuple(class_names), np.arange(k), X.shape[1]
    for t, reg in regs.items():
        Y = getattr(data, f"eta_{t}")
        params = {**reg._xgb_params(), "objective": "reg:squarederror", "base_score": 0.0}
        reg.boosters_ = []
        for i in range(3):
            d = dxgb.DaskDMatrix(client, X, col(np.ascontiguousarray(Y[:, i])), feature_names=names)
            reg.boosters_.append(dxgb.train(client, params, d, num_boost_round=int(reg.n_estimators))["booster"])
        reg.schema_, reg.n_features_in_ = schema, X.shape[1]
    return clf, regs
