"""Feature training ranges and the out-of-range fallback.

At training, each feature's range over the training windows is stored in the model's
``metadata.json`` (``feature_ranges``: the ``RANGE_QUANTILES`` quantiles per feature, in the
schema's column order, plus the fallback threshold). When the filter runs, a window whose features
lie outside that range on *more than* a fraction ``max_out_of_range`` of the bounded features is
not predicted at all: its prediction row is NaN ("no prediction"), which every prediction-driven
filter treats as its documented default (the VQF core's own settings for ``vqf_toggling``; the
toggling CF's core gains, ``filters.toggling`` step 4). The models are not trusted where they never saw data.

Why a count and not a per-feature test: with 0.5–99.5 % bounds each feature is outside its range
on 1 % of the training windows, so with ~70 features an ordinary window is often outside on one
or two; a window unlike the training data is outside on many at once. The threshold is a fraction
of the bounded features.

The same rule runs in the compiled loop (``out_of_range_count``, numba) and vectorised
(``windows_out_of_range``) for learning gains from held predictions: both count with the same
float64 comparisons.
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit

__all__ = ["RANGE_QUANTILES", "DEFAULT_MAX_OUT_OF_RANGE", "feature_ranges", "range_arrays", "out_of_range_count",
           "window_out_of_range", "windows_out_of_range"]

#: lower and upper quantile of a feature's training values that bound its range
RANGE_QUANTILES = (0.005, 0.995)
#: default fallback threshold: more than this fraction of the bounded features out of range -> no
#: prediction (chosen before any cross-dataset result was seen; ``[run] max_out_of_range``)
DEFAULT_MAX_OUT_OF_RANGE = 0.2


def feature_ranges(X, names, max_out_of_range: float = DEFAULT_MAX_OUT_OF_RANGE,
                   quantiles=RANGE_QUANTILES) -> dict:
    """The ``feature_ranges`` record of a model's metadata: per feature (``names``, the columns of
    ``X (n, F)``, NaN = missing) the ``quantiles`` of its finite training values (``None`` when a
    feature has none), and the fallback threshold."""
    X = np.asarray(X, np.float64)
    if X.ndim != 2 or X.shape[1] != len(names):
        raise ValueError(f"feature_ranges: X must have shape (n, {len(names)}), got {X.shape}")
    if not 0.0 <= max_out_of_range <= 1.0:
        raise ValueError(f"max_out_of_range must be a fraction in [0, 1], got {max_out_of_range}")
    low, high = [], []
    for j in range(X.shape[1]):
        col = X[:, j][np.isfinite(X[:, j])]
        lo, hi = (np.quantile(col, quantiles).tolist() if col.size else (None, None))
        low.append(lo)
        high.append(hi)
    return {"quantiles": list(quantiles), "max_out_of_range": float(max_out_of_range), "names": list(names),
            "low": low, "high": high}


def range_arrays(ranges: dict | None, names) -> tuple[np.ndarray, np.ndarray, float]:
    """``(low, high, max_out_of_range)`` for the columns ``names`` (NaN: unbounded) from a
    ``feature_ranges`` record; no record (``None``): every feature unbounded, the fallback never fires."""
    n = len(names)
    if ranges is None:
        return np.full(n, np.nan), np.full(n, np.nan), 1.0
    if list(ranges["names"]) != list(names):
        raise ValueError("feature_ranges: its feature names differ from the model's schema")
    low = np.array([np.nan if v is None else v for v in ranges["low"]], np.float64)
    high = np.array([np.nan if v is None else v for v in ranges["high"]], np.float64)
    return low, high, float(ranges["max_out_of_range"])


@njit(cache=True)
def out_of_range_count(feat, low, high):
    """(n_out, n_bounded): features with finite bounds, and those of them whose finite value lies
    below ``low`` or above ``high``."""
    n_out = 0
    n_b = 0
    for j in range(feat.shape[0]):
        lo, hi = low[j], high[j]
        if math.isfinite(lo) and math.isfinite(hi):
            n_b += 1
            v = feat[j]
            if math.isfinite(v) and (v < lo or v > hi):
                n_out += 1
    return n_out, n_b


@njit(cache=True)
def window_out_of_range(feat, low, high, max_out_of_range):
    """True when more than ``max_out_of_range`` of the bounded features of ``feat`` are out of range."""
    n_out, n_b = out_of_range_count(feat, low, high)
    return n_out > max_out_of_range * n_b


@njit(cache=True)
def _rows_out_of_range(X, low, high, max_out_of_range, out):
    for i in range(X.shape[0]):
        out[i] = window_out_of_range(X[i], low, high, max_out_of_range)


def windows_out_of_range(X, low, high, max_out_of_range: float) -> np.ndarray:
    """``window_out_of_range`` of every row of ``X (n, F)``: bool ``(n,)``."""
    X = np.ascontiguousarray(X, dtype=np.float64)
    out = np.zeros(X.shape[0], np.bool_)
    _rows_out_of_range(X, np.asarray(low, np.float64), np.asarray(high, np.float64), float(max_out_of_range), out)
    return out
