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

``FlatForest.complete()`` re-lays the same trees out for speed in the filter loop
(``CompleteForest``, ``predict_margin_row_complete``): each tree padded to a complete binary tree
stored breadth-first (children of node ``i`` at ``2i+1``, ``2i+2``: no child pointers, one compare
per level, no data-dependent branch), eight trees walked side by side. Same leaves, same sums in
the same order: bit-identical margins (test).
"""
from __future__ import annotations

import json
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
from numba import njit

from togglecf.core.extras import require

__all__ = ["FlatForest", "FlatForestArrays", "CompleteForest", "CompleteForestArrays", "COMPLETE_MAX_DEPTH",
           "predict_margin_row", "predict_margin_row_complete", "sigmoid", "softmax"]

_SUPPORTED = {"binary:logistic": "sigmoid", "multi:softprob": "softmax", "multi:softmax": "softmax",
              "reg:squarederror": "identity", "reg:pseudohubererror": "identity", "reg:absoluteerror": "identity"}
#: the arrays of a ``FlatForest`` and their dtypes (``to_dict``/``from_dict``)
_ARRAY_DTYPES = {"feature": np.int32, "threshold": np.float32, "left": np.int32, "right": np.int32,
                 "default_left": np.bool_, "value": np.float32, "roots": np.int32, "tree_group": np.int32,
                 "base_margin": np.float64}


class FlatForestArrays(NamedTuple):
    """The arrays of a ``FlatForest`` as one record (compiled to a struct) for ``predict_margin_row``
    (``FlatForest.arrays()``; ``n_nodes`` nodes, ``n_trees`` trees, ``n_outputs`` outputs)."""

    feature: np.ndarray  # (n_nodes,) int32 split feature, -1 for a leaf
    threshold: np.ndarray  # (n_nodes,) float32 split value (go left when x < threshold)
    left: np.ndarray  # (n_nodes,) int32 absolute child indices (-1 for leaves)
    right: np.ndarray
    default_left: np.ndarray  # (n_nodes,) bool, branch for a missing (NaN) feature
    value: np.ndarray  # (n_nodes,) float32 leaf value
    roots: np.ndarray  # (n_trees,) int32 root node of each tree
    tree_group: np.ndarray  # (n_trees,) int32 output each tree adds to
    base_margin: np.ndarray  # (n_outputs,) float64 margin before any tree


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

    def depths(self) -> np.ndarray:
        """``(n_trees,)`` depth of each tree (0: a single leaf)."""
        out = np.zeros(len(self.roots), np.int32)
        for t, root in enumerate(self.roots):
            stack = [(int(root), 0)]
            while stack:
                node, d = stack.pop()
                if self.feature[node] >= 0:
                    stack += [(int(self.left[node]), d + 1), (int(self.right[node]), d + 1)]
                else:
                    out[t] = max(out[t], d)
        return out

    def complete(self) -> "CompleteForest":
        """The same forest as complete binary trees (``CompleteForest``) for
        ``predict_margin_row_complete``: identical margins, several times faster to walk.
        Raises ``ValueError`` for trees deeper than ``COMPLETE_MAX_DEPTH`` (the padded layout
        grows as 2^depth) or a threshold that is NaN or −inf (the missing-value encoding needs
        ``-inf < threshold``)."""
        inner = self.feature >= 0
        if not np.all(self.threshold[inner] > -np.inf):
            raise ValueError("complete(): a split threshold is NaN or -inf")
        if np.any(inner & ((self.left < 0) | (self.right < 0))):
            raise ValueError("complete(): an inner node without children")
        tree_depth = self.depths()
        if tree_depth.size and tree_depth.max() > COMPLETE_MAX_DEPTH:
            raise ValueError(f"complete(): trees deeper than {COMPLETE_MAX_DEPTH} levels")
        n_trees, F = len(self.roots), self.n_features
        # every block of _BLOCK trees walked side by side shares one depth: the deepest of the block
        depth = tree_depth.copy()
        for b in range(0, n_trees - n_trees % _BLOCK, _BLOCK):
            depth[b:b + _BLOCK] = tree_depth[b:b + _BLOCK].max()
        inner_offset = np.zeros(n_trees, np.int32)
        leaf_offset = np.zeros(n_trees, np.int32)
        if n_trees:
            inner_offset[1:] = np.cumsum((1 << depth[:-1].astype(np.int64)) - 1)
            leaf_offset[1:] = np.cumsum(1 << depth[:-1].astype(np.int64))
        n_inner = int(inner_offset[-1] + (1 << int(depth[-1])) - 1) if n_trees else 0
        n_leaf = int(leaf_offset[-1] + (1 << int(depth[-1]))) if n_trees else 0
        # padding nodes read the constant slot F (0.0) against +inf: always left
        feature = np.full(n_inner, F, np.int32)
        threshold = np.full(n_inner, np.inf, np.float32)
        value = np.zeros(n_leaf, np.float32)
        for t in range(n_trees):
            D, io, lo = int(depth[t]), int(inner_offset[t]), int(leaf_offset[t])
            stack = [(int(self.roots[t]), 0, 0)]  # (node, breadth-first index, level)
            while stack:
                node, i, d = stack.pop()
                if d == D:
                    value[lo + i - ((1 << D) - 1)] = self.value[node]
                elif self.feature[node] < 0:  # a leaf above the padded depth: continue left to the bottom
                    stack.append((node, 2 * i + 1, d + 1))
                else:
                    # missing values: the row holds each feature twice, NaN as -inf (goes left) at j and as
                    # +inf (goes right) at F + 1 + j; a node reads the copy of its default branch
                    f = int(self.feature[node])
                    feature[io + i] = f if self.default_left[node] else F + 1 + f
                    threshold[io + i] = self.threshold[node]
                    stack.append((int(self.left[node]), 2 * i + 1, d + 1))
                    stack.append((int(self.right[node]), 2 * i + 2, d + 1))
        return CompleteForest(feature, threshold, value, inner_offset, leaf_offset, depth.astype(np.int32),
                              np.ascontiguousarray(self.tree_group, np.int32), self.base_margin.copy(), F)

    def _base_margin_from(self, booster) -> np.ndarray:
        """The booster's margin for an all-missing row minus our leaf sum for it (version-proof)."""
        xgb = require("xgboost", extra="train", what="flattening an XGBoost booster")
        row = np.full((1, self.n_features), np.nan, np.float32)
        ours = self.predict_margin(row, base=np.zeros(self.n_outputs))[0]
        dm = xgb.DMatrix(row, missing=np.nan, feature_names=booster.feature_names)  # named models insist on names
        theirs = np.asarray(booster.predict(dm, output_margin=True), np.float64)
        return theirs.reshape(-1)[: self.n_outputs] - ours

    def as_arrays(self) -> dict:
        """Name -> array of every node and tree array (the dict ``from_dict`` takes, beside ``link`` and
        ``n_features``)."""
        return {k: getattr(self, k) for k in _ARRAY_DTYPES}

    def to_dict(self) -> dict:
        """The forest in JSON types (``json.dumps`` writes it, ``from_dict`` reads it back bit for bit:
        a float32 is exactly a float64, and JSON keeps every float64)."""
        return {**{k: v.tolist() for k, v in self.as_arrays().items()}, "link": self.link,
                "n_features": int(self.n_features)}

    @classmethod
    def from_dict(cls, d: dict) -> "FlatForest":
        """The forest ``to_dict`` (or ``as_arrays`` with ``link`` and ``n_features``) wrote (numpy alone:
        no XGBoost); refused when its arrays disagree in length."""
        arrays = {k: np.ascontiguousarray(np.asarray(d[k], dtype=dt)) for k, dt in _ARRAY_DTYPES.items()}
        forest = cls(**arrays, link=str(d["link"]), n_features=int(d["n_features"]))
        n = forest.n_nodes
        if any(len(arrays[k]) != n for k in ("threshold", "left", "right", "default_left", "value")) or \
                len(forest.tree_group) != len(forest.roots):
            raise ValueError("forest arrays of inconsistent lengths")
        return forest

    def arrays(self) -> FlatForestArrays:
        """The forest as the record ``predict_margin_row`` walks."""
        return FlatForestArrays(self.feature, self.threshold, self.left, self.right, self.default_left, self.value,
                                self.roots, self.tree_group, self.base_margin)

    def predict_margin(self, X, base=None) -> np.ndarray:
        """Raw margins ``(n, n_outputs)`` for features ``X (n, n_features)`` (NaN = missing)."""
        X = np.ascontiguousarray(X, dtype=np.float32)
        if X.ndim != 2 or X.shape[1] != self.n_features:
            raise ValueError(f"features: expected shape (n, {self.n_features}), got {X.shape}")
        out = np.empty((X.shape[0], self.n_outputs))
        arrays = self.arrays()
        if base is not None:
            arrays = arrays._replace(base_margin=np.asarray(base, np.float64))
        _predict_matrix(X, arrays, out)
        return out

    def predict(self, X) -> np.ndarray:
        """Probabilities (classifiers: ``(n,)`` for binary, ``(n, k)`` for multi-class) or values."""
        m = self.predict_margin(X)
        if self.link == "sigmoid":
            return sigmoid(m[:, 0])
        if self.link == "softmax":
            return softmax(m)
        return m[:, 0] if self.n_outputs == 1 else m


#: deepest tree ``FlatForest.complete`` lays out (2^depth − 1 nodes per tree)
COMPLETE_MAX_DEPTH = 12
#: trees walked side by side by ``predict_margin_row_complete`` (independent chains of loads keep the
#: CPU busy while each waits for its memory; the blocks of this many trees share one padded depth)
_BLOCK = 8


class CompleteForestArrays(NamedTuple):
    """The arrays of a ``CompleteForest`` as one record (compiled to a struct) for
    ``predict_margin_row_complete`` (``CompleteForest.arrays()``; ``F`` features, ``n_trees`` trees)."""

    row: np.ndarray  # (2 F + 2,) float32 scratch: the doubled feature row (overwritten by every walk)
    feature: np.ndarray  # (n_inner,) int32 index into the doubled row
    threshold: np.ndarray  # (n_inner,) float32
    value: np.ndarray  # (n_leaf,) float32 leaf values
    inner_offset: np.ndarray  # (n_trees,) int32 first inner node of each tree
    leaf_offset: np.ndarray  # (n_trees,) int32 first leaf of each tree
    depth: np.ndarray  # (n_trees,) int32 padded depth of each tree
    tree_group: np.ndarray  # (n_trees,) int32 output each tree adds to
    base_margin: np.ndarray  # (n_outputs,) float64 margin before any tree


@dataclass
class CompleteForest:
    """A ``FlatForest`` with each tree padded to a complete binary tree (``FlatForest.complete``).

    Tree ``t`` has ``2^depth[t] − 1`` inner nodes from ``inner_offset[t]`` (breadth-first: node ``i``
    has children ``2i+1`` (left) and ``2i+2``) and ``2^depth[t]`` leaves from ``leaf_offset[t]``.
    A leaf above the full depth continues through padding nodes that always go left. ``feature``
    indexes the doubled row of ``predict_margin_row_complete``: ``j`` where a missing value goes
    left, ``n_features + 1 + j`` where it goes right, ``n_features`` (a constant 0.0) for padding
    (threshold +inf).
    """

    feature: np.ndarray
    threshold: np.ndarray
    value: np.ndarray
    inner_offset: np.ndarray
    leaf_offset: np.ndarray
    depth: np.ndarray
    tree_group: np.ndarray
    base_margin: np.ndarray
    n_features: int

    def arrays(self) -> CompleteForestArrays:
        """The forest as the record ``predict_margin_row_complete`` walks (with a fresh row buffer)."""
        return CompleteForestArrays(np.zeros(2 * self.n_features + 2, np.float32), self.feature, self.threshold,
                                    self.value, self.inner_offset, self.leaf_offset, self.depth, self.tree_group,
                                    self.base_margin)


def sigmoid(m):
    return 1.0 / (1.0 + np.exp(-np.asarray(m, float)))


def softmax(m):
    m = np.asarray(m, float)
    e = np.exp(m - m.max(axis=-1, keepdims=True))
    return e / e.sum(axis=-1, keepdims=True)


@njit(cache=True)
def predict_margin_row(x, forest, out):
    """Margins of one feature row ``x (n_features,)`` (float32 or float64; NaN = missing) into
    ``out (n_outputs,)`` float64, walking ``forest`` (a ``FlatForestArrays``)."""
    feature, threshold, left, right = forest.feature, forest.threshold, forest.left, forest.right
    default_left, value, roots, tree_group = forest.default_left, forest.value, forest.roots, forest.tree_group
    base_margin = forest.base_margin
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


#: the walk's indices are unsigned: numba checks every signed index for a negative (wraparound) value,
#: a compare and a select in each level's dependency chain
_U = np.uint64


@njit(cache=True, inline="always")
def _level(xs, feature, threshold, base, i):
    """One level down a complete tree: left (2i+1) when x < threshold, else right (2i+2); ``base``,
    ``i`` unsigned (``_U``)."""
    j = base + i
    return _U(2) * i + _U(2) - _U(xs[_U(feature[j])] < threshold[j])


@njit(cache=True)
def predict_margin_row_complete(x, forest, out):
    """``predict_margin_row`` on a ``CompleteForest`` (``forest`` a ``CompleteForestArrays``, from
    ``CompleteForest.arrays()``; its ``row`` the float32 scratch of ``2 F + 2``): the same margins
    ``out (n_outputs,)`` bit for bit. ``x (F,)`` as float32, NaN as −inf at ``j`` and +inf at
    ``F + 1 + j`` (``x < threshold`` then follows the default branch, and ±inf inputs compare as
    before); eight trees walked side by side; leaves added in tree order."""
    xs, feature, threshold, value = forest.row, forest.feature, forest.threshold, forest.value
    inner_offset, leaf_offset, depth = forest.inner_offset, forest.leaf_offset, forest.depth
    tree_group, base_margin = forest.tree_group, forest.base_margin
    F = x.shape[0]
    for j in range(F):
        v = np.float32(x[j])
        if np.isnan(v):
            xs[j] = -np.inf
            xs[F + 1 + j] = np.inf
        else:
            xs[j] = v
            xs[F + 1 + j] = v
    xs[F] = 0.0
    xs[2 * F + 1] = 0.0
    for k in range(out.shape[0]):
        out[k] = base_margin[k]
    T = inner_offset.shape[0]
    t = 0
    while t + 8 <= T:  # blocks of _BLOCK = 8 trees of one (padded) depth
        D = depth[t]
        b0, b1, b2, b3 = (_U(inner_offset[t]), _U(inner_offset[t + 1]), _U(inner_offset[t + 2]),
                          _U(inner_offset[t + 3]))
        b4, b5, b6, b7 = (_U(inner_offset[t + 4]), _U(inner_offset[t + 5]), _U(inner_offset[t + 6]),
                          _U(inner_offset[t + 7]))
        i0 = i1 = i2 = i3 = i4 = i5 = i6 = i7 = _U(0)
        for _ in range(D):
            i0 = _level(xs, feature, threshold, b0, i0)
            i1 = _level(xs, feature, threshold, b1, i1)
            i2 = _level(xs, feature, threshold, b2, i2)
            i3 = _level(xs, feature, threshold, b3, i3)
            i4 = _level(xs, feature, threshold, b4, i4)
            i5 = _level(xs, feature, threshold, b5, i5)
            i6 = _level(xs, feature, threshold, b6, i6)
            i7 = _level(xs, feature, threshold, b7, i7)
        first = _U((1 << D) - 1)  # breadth-first index of the first leaf
        out[tree_group[t]] += value[_U(leaf_offset[t]) + i0 - first]
        out[tree_group[t + 1]] += value[_U(leaf_offset[t + 1]) + i1 - first]
        out[tree_group[t + 2]] += value[_U(leaf_offset[t + 2]) + i2 - first]
        out[tree_group[t + 3]] += value[_U(leaf_offset[t + 3]) + i3 - first]
        out[tree_group[t + 4]] += value[_U(leaf_offset[t + 4]) + i4 - first]
        out[tree_group[t + 5]] += value[_U(leaf_offset[t + 5]) + i5 - first]
        out[tree_group[t + 6]] += value[_U(leaf_offset[t + 6]) + i6 - first]
        out[tree_group[t + 7]] += value[_U(leaf_offset[t + 7]) + i7 - first]
        t += 8
    while t < T:
        D = depth[t]
        i = _U(0)
        for _ in range(D):
            i = _level(xs, feature, threshold, _U(inner_offset[t]), i)
        out[tree_group[t]] += value[_U(leaf_offset[t]) + i - _U((1 << D) - 1)]
        t += 1


@njit(cache=True)
def _predict_matrix(X, forest, out):
    """``predict_margin_row`` of each row of ``X (n, n_features)`` into ``out (n, n_outputs)``."""
    for i in range(X.shape[0]):
        predict_margin_row(X[i], forest, out[i])
