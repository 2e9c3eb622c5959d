"""The two fold protocols by whole trial, in one place.

* ``trial_folds``: the held-out study's and the pruning sweep's outer folds: round-robin over the
  sorted trial names, so every fold mixes BROAD's groups; deterministic and independent of sizes.
* ``window_group_folds``: the inner cross-validation of ``togglecf train`` (``GroupKFold`` with the
  trial as group: folds balanced by number of windows).

They differ because they were chosen for different jobs (a readable, stable outer split; CV folds
of similar size); merging them would change every published number, so both stay, named.
"""
from __future__ import annotations

import numpy as np

from togglecf.core.extras import require

__all__ = ["trial_folds", "window_group_folds"]


def trial_folds(names, k: int, seed: int = 0) -> list[list[str]]:
    """``k`` test sets by whole trial: round-robin over the sorted names (deterministic). Another
    ``seed`` > 0 shuffles the sorted names first (with ``numpy.random.default_rng(seed)``): another
    fold assignment, to measure how much the results move with it."""
    names = sorted(names)
    if seed:
        names = [names[i] for i in np.random.default_rng(seed).permutation(len(names))]
    if not 2 <= k <= len(names):
        raise ValueError(f"need 2 <= folds <= number of trials ({len(names)}), got {k}")
    return [names[i::k] for i in range(k)]


def window_group_folds(group: np.ndarray, n_trials: int, n_splits: int):
    """``[(train_trials, test_trials), ...]`` from ``GroupKFold`` on the trial of every window."""
    k = max(2, min(int(n_splits), n_trials))
    if n_trials < 2:
        raise ValueError("cross-validation by trial needs at least 2 trials")
    dummy = np.zeros(len(group))
    folds = []
    model_selection = require("sklearn.model_selection", extra="train", what="cross-validation by trial")
    for tr, te in model_selection.GroupKFold(n_splits=k).split(dummy, groups=group):
        folds.append((np.unique(group[tr]), np.unique(group[te])))
    return folds
