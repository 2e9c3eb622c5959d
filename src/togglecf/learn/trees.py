"""XGBoost tree ensembles flattened into arrays, traversed in numba.

The toggling filter runs its models inside the compiled filter loop, so the trees cannot
be called through ``xgboost``. ``FlatForest.from_booster`` reads a trained booster's JSON
dump into flat node arrays; ``predict_margin_row`` walks them for one feature row from
``@njit`` code; ``FlatForest.predict`` does the same for a matrix and applies the
objective's link (sigmoid, softmax or identity). This is also the compact "array" format
for embedded export (about 12 bytes per node: feature, threshold, children, leaf value).

XGBoost's semantics, reproduced exactly:
* features are compared as float32: go left when ``float32(x) < threshold``;
* a missing (NaN) feature follows the node's ``default_left`` branch;
* tree ``t`` adds its leaf value to output ``tree_group[t]`` (the class for multi-class);
* the base margin is taken from the booster itself (``base_score`` in margin space).
"""
from __future__ import annotations

import json
from dataclasses import dataclass

import numpy as np
from numba import njit

__all__ = ["FlatForest", "predict_margin_row", "sigmoid", "softmax"]

_SUPPORTED = {"binary:logistic": "sigmoid", "multi:softprob": "softmax", "multi:softmax": "softmax",
              "reg:squarederror": "identity", "reg:pseudohubererror": "identity", "reg:absoluteerror": "identity"}


@dataclass
class FlatForest:
    """A tree ensemble as flat arrays (node ``i`` of the whole forest).

    Attributes:
        feature: ``(n_nodes,)`` int32 split feature, -1 for a leaf.
        threshold: ``(n_nodes,)`` float32 split value (go left when x < threshold).
        left, right: ``(n_nodes,)`` int32 absolute child indices (-1 for leaves).
        default_left: ``(n_nodes,)`` bool, branch for a missing (NaN) feature.
        value: ``(n_nodes,)`` float32 leaf value (0 for inner nodes).
        roots: ``(n_trees,)`` int32 root node index of each tree.
        tree_group: ``(n_trees,)`` int32 output each tree adds to.
        base_margin: ``(n_outputs,)`` float64 margin before any tree.
        link: ``'sigmoid'``, ``'softmax'`` or ``'identity'``.
        n_features: number of input features.
    """

    feature: np.ndarray
    threshold: np.ndarray
    left: np.ndarray
    right: np.ndarray
    default_left: np.ndarray
    value: np.ndarray
    roots: np.ndarray
    tree_group: np.ndarray
    base_margin: np.ndarray
    link: str
    n_features: int

    @property
    def n_outputs(self) -> int:
        return len(self.base_margin)

    @property
    def n_nodes(self) -> int:
        return len(self.feature)

    @classmethod
    def from_booster(cls, booster) -> "FlatForest":
        """Flatten an ``xgboost.Booster`` (or a fitted ``XGBModel``; gbtree, numeric splits)."""
        if hasattr(booster, "get_booster"):
            booster = booster.get_booster()
        model = json.loads(booster.save_raw("json"))
        learner = model["learner"]
        objective = learner["objective"]["name"]
        if objective not in _SUPPORTED:
            raise ValueError(f"objective {objective!r} not supported; supported: {sorted(_SUPPORTED)}")
        gb = learner["gradient_booster"]
        if gb.get("name", "gbtree") != "gbtree":
            raise ValueError(f"only gbtree boosters can be flattened, got {gb.get('name')!r}")
        trees = gb["model"]["trees"]
        n_features = int(learner["learner_model_param"]["num_feature"])
        n_class = int(learner["learner_model_param"].get("num_class", "0"))
        n_outputs = max(1, n_class, int(learner["learner_model_param"].get("num_target", "1")))
        feature, threshold, left, right, default_left, value, roots = [], [], [], [], [], [], []
        offset = 0
        for t in trees:
            if any(int(s) != 0 for s in t.get("split_type", [])):
                raise ValueError("categorical splits are not supported")
            lc = np.asarray(t["left_children"], np.int64)
            rc = np.asarray(t["right_children"], np.int64)
            leaf = lc == -1
            cond = np.asarray(t["split_conditions"], np.float32)
            roots.append(offset)
            feature.append(np.where(leaf, -1, np.asarray(t["split_indices"], np.int64)))
            threshold.append(np.where(leaf, np.float32(0), cond))
            left.append(np.where(leaf, -1, lc + offset))
            right.append(np.where(leaf, -1, rc + offset))
            default_left.append(np.asarray(t["default_left"], bool))
            value.append(np.where(leaf, cond, np.float32(0)))  # a leaf's value is stored as its condition
            offset += len(lc)
        cat = (lambda parts, dt: np.ascontiguousarray(np.concatenate(parts).astype(dt)) if parts
               else np.zeros(0, dt))
        forest = cls(cat(feature, np.int32), cat(threshold, np.float32), cat(left, np.int32), cat(right, np.int32),
                     cat(default_left, np.bool_), cat(value, np.float32), np.asarray(roots, np.int32),
                     np.asarray(gb["model"]["tree_info"], np.int32), np.zeros(n_outputs), _SUPPORTED[objective],
                     n_features)
        forest.base_margin = forest._base_margin_from(booster)
        return forest

    @classmethod
    def concatenate(cls, forests) -> "FlatForest":
        """One forest whose outputs are those of ``forests`` one after another (e.g. class
        margins, then η_a x/y/z, then η_m x/y/z): a single traversal loop serves all models.
        The link is ``'identity'``: callers apply each block's own link to its margins."""
        forests = list(forests)
        if not forests or len({f.n_features for f in forests}) != 1:
            raise ValueError("forests to concatenate must exist and share their number of features")
        parts, node_off, out_off = {k: [] for k in ("feature", "threshold", "left", "right", "default_left", "value",
                                                    "roots", "tree_group")}, 0, 0
        for f in forests:
            inner = f.left >= 0
            parts["feature"].append(f.feature)
            parts["threshold"].append(f.threshold)
            parts["left"].append(np.where(inner, f.left + node_off, -1))
            parts["right"].append(np.where(inner, f.right + node_off, -1))
            parts["default_left"].append(f.default_left)
            parts["value"].append(f.value)
            parts["roots"].append(f.roots + node_off)
            parts["tree_group"].append(f.tree_group + out_off)
            node_off += f.n_nodes
            out_off += f.n_outputs
        dtypes = {"feature": np.int32, "threshold": np.float32, "left": np.int32, "right": np.int32,
                  "default_left": np.bool_, "value": np.float32, "roots": np.int32, "tree_group": np.int32}
        arrays = {k: np.ascontiguousarray(np.concatenate(v).astype(dtypes[k])) for k, v in parts.items()}
        return cls(**arrays, base_margin=np.concatenate([f.base_margin for f in forests]), link="identity",
                   n_features=forests[0].n_features)

    def without_outputs(self, outputs) -> "FlatForest":
        """The same forest with the trees of ``outputs`` not walked (those outputs then stay at
        their base margin). For outputs a caller multiplies by zero: their trees cost time only."""
        keep = ~np.isin(self.tree_group, np.asarray(list(outputs), np.int32))
        return FlatForest(self.feature, self.threshold, self.left, self.right, self.default_left, self.value,
                          np.ascontiguousarray(self.roots[keep]), np.ascontiguousarray(self.tree_group[keep]),
                          self.base_margin.copy(), self.link, self.n_features)

    def _base_margin_from(self, booster) -> np.ndarray:
        """The booster's margin for an all-missing row minus our leaf sum for it (version-proof)."""
        import xgboost as xgb

        row = np.full((1, self.n_features), np.nan, np.float32)
        ours = self.predict_margin(row, base=np.zeros(self.n_outputs))[0]
        dm = xgb.DMatrix(row, missing=np.nan, feature_names=booster.feature_names)  # named models insist on names
        theirs = np.asarray(booster.predict(dm, output_margin=True), np.float64)
        return theirs.reshape(-1)[: self.n_outputs] - ours

    def arrays(self):
        """The tuple of arrays ``predict_margin_row`` takes after the feature row."""
        return (self.feature, self.threshold, self.left, self.right, self.default_left, self.value, self.roots,
                self.tree_group, self.base_margin)

    def predict_margin(self, X, base=None) -> np.ndarray:
        """Raw margins ``(n, n_outputs)`` for features ``X (n, n_features)`` (NaN = missing)."""
        X = np.ascontiguousarray(X, dtype=np.float32)
        if X.ndim != 2 or X.shape[1] != self.n_features:
            raise ValueError(f"features: expected shape (n, {self.n_features}), got {X.shape}")
        out = np.empty((X.shape[0], self.n_outputs))
        arrs = list(self.arrays())
        if base is not None:
            arrs[-1] = np.asarray(base, np.float64)
        _predict_matrix(X, *arrs, out)
        return out

    def predict(self, X) -> np.ndarray:
        """Probabilities (classifiers: ``(n,)`` for binary, ``(n, k)`` for multi-class) or values."""
        m = self.predict_margin(X)
        if self.link == "sigmoid":
            return sigmoid(m[:, 0])
        if self.link == "softmax":
            return softmax(m)
        return m[:, 0] if self.n_outputs == 1 else m


def sigmoid(m):
    return 1.0 / (1.0 + np.exp(-np.asarray(m, float)))


def softmax(m):
    m = np.asarray(m, float)
    e = np.exp(m - m.max(axis=-1, keepdims=True))
    return e / e.sum(axis=-1, keepdims=True)


@njit(cache=True)
def predict_margin_row(x, feature, threshold, left, right, default_left, value, roots, tree_group, base_margin, out):
    """Margins of one feature row ``x`` (float32 or float64; NaN = missing) into ``out``."""
    for k in range(out.shape[0]):
        out[k] = base_margin[k]
    for t in range(roots.shape[0]):
        node = roots[t]
        while feature[node] >= 0:
            v = np.float32(x[feature[node]])
            if np.isnan(v):
                node = left[node] if default_left[node] else right[node]
            elif v < threshold[node]:
                node = left[node]
            else:
                node = right[node]
        out[tree_group[t]] += value[node]


@njit(cache=True)
def _predict_matrix(X, feature, threshold, left, right, default_left, value, roots, tree_group, base_margin, out):
    for i in range(X.shape[0]):
        predict_margin_row(X[i], feature, threshold, left, right, default_left, value, roots, tree_group,
                           base_margin, out[i])
