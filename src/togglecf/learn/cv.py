"""Cross-validation by whole trial: per-fold and pooled metrics, and out-of-fold predictions.

Every window of a test trial is left out of that fold's training (folds from
``learn.folds.window_group_folds``). Training windows are those whose end sample has valid
targets (and, with ``ransac = true``, is a RANSAC inlier); test windows are always the valid
RANSAC inliers of the test trials, so switching RANSAC changes the training data only and its
effect can be compared on the same test set. Baselines: the majority class of the fold's
training labels (classifier) and zero noise (regressors).
"""
from __future__ import annotations

import time

import numpy as np

from togglecf.data.broad import short_trial_name
from togglecf.learn.compiled import CompiledModels
from togglecf.learn.dataset import WindowData
from togglecf.learn.fitting import fit_all, score_fold
from togglecf.learn.folds import window_group_folds
from togglecf.learn.models import ModelBundle, classification_metrics, regression_metrics
from togglecf.learn.ranges import feature_ranges
from togglecf.parallel.backend import InlineBackend

__all__ = ["cross_validate", "cv_fold", "format_cv_table"]


def cv_fold(cfg, data: WindowData, i, train_g, test_g, schema, class_names):
    """One CV fold (a task): fit on the training trials' rows, score the held-out ones, and the
    out-of-fold predictions on every window of the held-out trials (for the gains)."""
    train_rows = np.flatnonzero(np.isin(data.group, train_g) & data.train_mask)
    test_rows = np.flatnonzero(np.isin(data.group, test_g) & data.eval_mask)
    t0 = time.perf_counter()
    clf, regs = fit_all(cfg, data, train_rows, schema, class_names)
    res, preds = score_fold(clf, regs, data, train_rows, test_rows, schema, len(class_names))
    # the fold's models as the filter runs them: with the out-of-range fallback of the range of every window of its
    # training trials (the filter meets all of them, not only those with valid RANSAC-inlier targets)
    ranges = feature_ranges(data.X[np.isin(data.group, train_g)], schema.names, cfg["run"]["max_out_of_range"])
    oof_models = CompiledModels.from_bundle(ModelBundle(clf, regs, schema, {"feature_ranges": ranges}))
    oof = {}
    for g in test_g:
        rows_g = np.flatnonzero(data.group == g)
        oof[data.trials[g]] = (data.end[rows_g], oof_models.predict_windows(data.X[rows_g]))
    res.update(fold=i, test_trials=[data.trials[g] for g in test_g],
               train_trials=[data.trials[g] for g in train_g], n_train=len(train_rows),
               n_test=len(test_rows), seconds=time.perf_counter() - t0)
    return res, preds, oof


def cross_validate(cfg, data: WindowData, schema, class_names, backend=None):
    """Per-fold and pooled CV metrics; ``folds`` records each fold's train/test trial names.
    Also returns the out-of-fold predictions: trial -> (window ends, prediction rows).

    Each fold is one task on ``backend`` (``togglecf.parallel.backend``; default: this process, fold after fold,
    each fold with ``[run] nthread`` XGBoost threads); on Dask the window data is scattered once and
    the folds train on the workers. Results are combined in fold order, so they do not depend on
    where or in which order the folds ran."""
    n_classes = len(class_names)
    folds = window_group_folds(data.group, len(data.trials), cfg["run"]["cv_folds"])
    backend = backend or InlineBackend()
    handle = backend.scatter(data)
    tasks = [(i, (cfg, handle, i, train_g, test_g, schema, class_names)) for i, (train_g, test_g) in enumerate(folds)]
    fold_out = {}
    for o in backend.run(cv_fold, tasks, desc="cross-validation", unit="fold"):
        if o.error is not None:
            raise o.error
        fold_out[o.key] = o.value
    out = {"folds": [], "per_trial": {}}
    oof = {}
    pooled = {"y": [], "proba": [], "const": [], "acc": [], "acc_t": [], "mag": [], "mag_t": []}
    for i, (train_g, test_g) in enumerate(folds):
        res, preds, oof_i = fold_out[i]
        oof.update(oof_i)
        test_rows = np.flatnonzero(np.isin(data.group, test_g) & data.eval_mask)
        out["folds"].append(res)
        for g in test_g:  # held-out numbers of every test trial on its own
            sel = data.group[test_rows] == g
            yt = data.state[test_rows][sel]
            m = classification_metrics(yt, preds["proba"][sel], n_classes)
            pt = {"fold": i, "n": int(sel.sum()), "balanced_accuracy": m["balanced_accuracy"], "f1_macro": m["f1_macro"]}
            for t in ("acc", "mag"):
                ytt = getattr(data, f"eta_{t}")[test_rows][sel]
                r = regression_metrics(ytt, preds[t][sel])
                pt.update({f"{t}_rmse": r["rmse"], f"{t}_r2": r["r2"],
                           f"{t}_rmse_zero": regression_metrics(ytt, np.zeros_like(ytt))["rmse"]})
            out["per_trial"][data.trials[g]] = pt
        pooled["y"].append(data.state[test_rows])
        pooled["proba"].append(preds["proba"])
        c = np.zeros_like(preds["proba"])
        c[:, res["majority"]["class"]] = 1.0
        pooled["const"].append(c)
        for t in ("acc", "mag"):
            pooled[t].append(preds[t])
            pooled[f"{t}_t"].append(getattr(data, f"eta_{t}")[test_rows])
    P = {k: np.concatenate(v) for k, v in pooled.items()}
    out["overall"] = {"classifier": classification_metrics(P["y"], P["proba"], n_classes),
                      "majority": classification_metrics(P["y"], P["const"], n_classes)}
    for t in ("acc", "mag"):
        out["overall"][t] = regression_metrics(P[f"{t}_t"], P[t])
        out["overall"][f"{t}_zero"] = regression_metrics(P[f"{t}_t"], np.zeros_like(P[f"{t}_t"]))
    return out, oof


def format_cv_table(cv: dict, class_names) -> str:
    head = (f"{'fold':>7} {'test trials':<22} {'n_test':>7} | {'balacc':>6} {'(maj)':>6} {'F1':>6} {'(maj)':>6} "
            f"{'AUC':>6} {'(maj)':>6} | {'accRMSE':>7} {'(zero)':>7} {'R2':>6} {'(zero)':>7} | "
            f"{'magRMSE':>7} {'(zero)':>7} {'R2':>6} {'(zero)':>7}")
    lines = [head, "-" * len(head)]

    def row(label, trials, r, n):
        c, m = r["classifier"], r["majority"]
        a, az, g, gz = r["acc"], r["acc_zero"], r["mag"], r["mag_zero"]
        return (f"{label:>7} {trials:<22} {n:>7d} | {c['balanced_accuracy']:6.3f} {m['balanced_accuracy']:6.3f} "
                f"{c['f1_macro']:6.3f} {m['f1_macro']:6.3f} {c['roc_auc']:6.3f} {m['roc_auc']:6.3f} | "
                f"{a['rmse']:7.3f} {az['rmse']:7.3f} {a['r2']:6.3f} {az['r2']:7.3f} | "
                f"{g['rmse']:7.3f} {gz['rmse']:7.3f} {g['r2']:6.3f} {gz['r2']:7.3f}")

    for f in cv["folds"]:
        lines.append(row(str(f["fold"]), ",".join(short_trial_name(t) for t in f["test_trials"])[:22], f, f["n_test"]))
    lines.append("-" * len(head))
    lines.append(row("overall", "pooled over folds", cv["overall"], cv["overall"]["classifier"]["n"]))
    conf = np.array(cv["overall"]["classifier"]["confusion"])
    lines.append("\npooled confusion matrix (rows true, columns predicted): " + ", ".join(class_names))
    w = max(len(c) for c in class_names)
    for name, r in zip(class_names, conf):
        lines.append(f"  {name:>{w}} " + " ".join(f"{v:8d}" for v in r))
    if cv.get("per_trial"):
        lines.append("\nper held-out trial: balanced accuracy | acc RMSE (zero) R² | mag RMSE (zero) R²")
        for name in sorted(cv["per_trial"]):
            p = cv["per_trial"][name]
            lines.append(f"  {name[:40]:40s} {p['balanced_accuracy']:6.3f} | {p['acc_rmse']:6.3f} ({p['acc_rmse_zero']:6.3f}) "
                         f"{p['acc_r2']:7.3f} | {p['mag_rmse']:6.3f} ({p['mag_rmse_zero']:6.3f}) {p['mag_r2']:7.3f}")
    lines.append("acc/mag: RMSE [m/s², µT] pooled over axes; R² = 1 − SSE/SST; (zero) = predicting no noise; "
                 "(maj) = majority class of the fold's training set")
    return "\n".join(lines)
