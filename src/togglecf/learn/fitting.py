"""Fitting the classifier and the noise regressors on training windows, and their feature importances."""
from __future__ import annotations

import numpy as np

from togglecf.learn.dataset import WindowData
from togglecf.learn.models import MotionClassifier, NoiseRegressor, classification_metrics, regression_metrics

__all__ = ["make_models", "fit_all", "fit_models", "gain_table", "feature_ranking", "score_fold", "importances_csv"]


def make_models(cfg):
    """Unfitted classifier and regressors (``{\"acc\", \"mag\"}``) of a training config."""
    run = cfg["run"]
    common = {"nthread": int(run["nthread"]), "seed": int(run["seed"])}
    clf = MotionClassifier(**cfg["classifier"], **common)
    regs = {t: NoiseRegressor(target=t, **cfg["regressor"], **common) for t in ("acc", "mag")}
    return clf, regs


def fit_all(cfg, data: WindowData, rows, schema, class_names):
    """Classifier and regressors on ``rows``. With ``[run] max_features = k`` (0: all), a first
    fit ranks the features (``feature_ranking``) and the models are refitted with only the top
    ``k`` present: the other columns are given as missing, so no tree splits on them (fewer
    features to compute on a microcontroller). The ranking uses the same training rows only."""
    X = data.X[rows]
    k = int(cfg["run"].get("max_features", 0) or 0)
    if 0 < k < X.shape[1]:
        keep = set(feature_ranking(*fit_models(cfg, X, data, rows, schema, class_names), schema)[:k])
        X = X.copy()
        X[:, [i for i, n in enumerate(schema.names) if n not in keep]] = np.nan
    return fit_models(cfg, X, data, rows, schema, class_names)


def fit_models(cfg, X, data: WindowData, rows, schema, class_names):
    clf, regs = make_models(cfg)
    clf.fit(X, data.state[rows], schema, class_names)
    regs["acc"].fit(X, data.eta_acc[rows], schema)
    regs["mag"].fit(X, data.eta_mag[rows], schema)
    return clf, regs


def gain_table(clf, regs, schema) -> dict:
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
    table = gain_table(clf, regs, schema)
    return sorted(schema.names, key=lambda n: -sum(t[n] for t in table.values()))


def score_fold(clf, regs, data: WindowData, train_rows, test_rows, schema, n_classes):
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


def importances_csv(clf, regs, schema) -> str:
    table = gain_table(clf, regs, schema)
    lines = ["feature," + ",".join(table)]
    for n in feature_ranking(clf, regs, schema):
        lines.append(n + "," + ",".join(f"{table[c][n]:.6f}" for c in table))
    return "\n".join(lines) + "\n"
