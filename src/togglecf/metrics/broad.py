"""BROAD's error metrics (Laidig et al. 2021, section "error metrics"; ../shared/docs/broad-metrics.md).

All angles returned in degrees unless a name says ``_rad``. Quaternions follow
``togglecf.core.quaternion`` (``[w,x,y,z]``, sensor -> ENU).
"""
from __future__ import annotations

import itertools
from dataclasses import dataclass

import numpy as np

from togglecf.core import quaternion as quat

__all__ = [
    "ErrorReference", "error_quaternion", "error_angles_rad", "remove_heading_offset", "rmse_deg", "trial_errors",
    "METRICS", "group_means", "tagp", "TagpResult",
]

#: Columns of ``trial_errors``; ``total``/``heading``/``inclination`` are BROAD's own.
METRICS = ("total", "heading", "inclination", "roll", "pitch", "yaw")


def error_quaternion(q_est, q_ref) -> np.ndarray:
    """Earth-frame error ``q_err = q_est ⊗ q_ref*`` of normalised inputs, normalised ``(N, 4)``."""
    return quat.normalize(quat.multiply(quat.normalize(q_est), quat.conjugate(quat.normalize(q_ref))))


def error_angles_rad(q_err) -> dict[str, np.ndarray]:
    """BROAD's per-sample total, heading and inclination errors [rad] of error quaternions."""
    w, z = q_err[..., 0], q_err[..., 3]
    with np.errstate(invalid="ignore", divide="ignore"):
        return {
            "total": 2.0 * np.arccos(np.clip(np.abs(w), 0.0, 1.0)),
            # 2·arctan(|z/w|), written with arctan2 so that w = 0 gives π rather than NaN
            "heading": 2.0 * np.arctan2(np.abs(z), np.abs(w)),
            "inclination": 2.0 * np.arccos(np.clip(np.sqrt(w * w + z * z), 0.0, 1.0)),
        }


def remove_heading_offset(q_est, q_ref, movement) -> np.ndarray:
    """6D estimates: rotate ``q_est`` about the vertical by the circular mean heading error
    over the scored samples, so a constant heading offset is not counted."""
    q_err = error_quaternion(q_est, q_ref)
    psi = 2.0 * np.arctan2(q_err[:, 3], q_err[:, 0])  # signed heading of the earth-frame error
    sel = np.asarray(movement, bool) & np.isfinite(psi)
    if not sel.any():
        return np.asarray(q_est, float)
    return _rotated_by_mean_heading(q_est, psi[sel])


def _rotated_by_mean_heading(q_est, psi) -> np.ndarray:
    """``q_est`` rotated about the vertical by minus the circular mean of the finite headings ``psi`` [rad]."""
    offset = np.arctan2(np.mean(np.sin(psi)), np.mean(np.cos(psi)))
    q_fix = np.array([np.cos(-offset / 2), 0.0, 0.0, np.sin(-offset / 2)])
    return quat.multiply(q_fix, q_est)


def _rmse_deg(e) -> float:
    if e.size == 0 or not np.isfinite(e).any():
        return float("nan")
    return float(np.degrees(np.sqrt(np.nanmean(e * e))))


def rmse_deg(err_rad, movement) -> float:
    """``sqrt(nanmean(e²))`` over the movement samples, in degrees (NaN when none is valid)."""
    return _rmse_deg(np.asarray(err_rad)[np.asarray(movement, bool)])


class ErrorReference:
    """The reference of one trial, prepared once to score many estimates of it (a grid, a gain
    search): ``ErrorReference(q_ref, movement).errors(q_est)`` equals ``trial_errors(q_est, q_ref,
    movement)`` bit for bit, computed on the scored samples only, with the reference's part
    (normalised conjugate, Euler angles) computed once.

    Args:
        q_ref: ``(N, 4)`` ground truth (NaN rows are ignored).
        movement: ``(N,)`` bool, the samples to score.
    """

    def __init__(self, q_ref, movement):
        q_ref = quat.as_quat(q_ref, "q_ref")
        movement = np.asarray(movement, bool)
        if not (q_ref.ndim == 2 and movement.shape == q_ref.shape[:1]):
            raise ValueError(f"shape mismatch: q_ref {q_ref.shape}, movement {movement.shape}")
        self.n_samples = q_ref.shape[0]
        self.movement = movement
        scored = q_ref[movement]
        self._ref_inverse = quat.conjugate(quat.normalize(scored))  # every error is per sample: the
        self._ref_euler = quat.to_euler_zyx(scored)                  # scored rows alone give the same RMSE

    def errors(self, q_est, six_d: bool = False) -> dict[str, float]:
        """RMSE [deg] of the ``(N, 4)`` estimate ``q_est``: BROAD's total/heading/inclination plus
        roll/pitch/yaw (``METRICS``); ``six_d``: remove the constant heading offset first."""
        q_est = quat.as_quat(q_est, "q_est")
        if q_est.shape != (self.n_samples, 4):
            raise ValueError(f"shape mismatch: q_est {q_est.shape}, q_ref ({self.n_samples}, 4)")
        q = q_est[self.movement]
        if six_d:
            q_err = self._error_quaternion(q)
            psi = 2.0 * np.arctan2(q_err[:, 3], q_err[:, 0])  # as remove_heading_offset
            if np.isfinite(psi).any():
                q = _rotated_by_mean_heading(q, psi[np.isfinite(psi)])
        out = {k: _rmse_deg(v) for k, v in error_angles_rad(self._error_quaternion(q)).items()}
        d = quat.to_euler_zyx(q) - self._ref_euler  # Euler-angle errors, wrapped to (-π, π]
        d = np.angle(np.exp(1j * d))
        for i, k in enumerate(("roll", "pitch", "yaw")):
            out[k] = _rmse_deg(d[:, i])
        return out

    def _error_quaternion(self, q) -> np.ndarray:
        """``error_quaternion`` of the scored rows ``q`` against the reference's."""
        return quat.normalize(quat.multiply(quat.normalize(q), self._ref_inverse))


def trial_errors(q_est, q_ref, movement, six_d: bool = False) -> dict[str, float]:
    """RMSE [deg] of one trial: BROAD's total/heading/inclination plus roll/pitch/yaw.

    Args:
        q_est: ``(N, 4)`` estimate.
        q_ref: ``(N, 4)`` ground truth (NaN rows are ignored).
        movement: ``(N,)`` bool, the samples to score.
        six_d: remove the constant heading offset first (estimates without magnetometer).
    Scoring many estimates of one trial: ``ErrorReference``.
    """
    q_est, q_ref = quat.as_quat(q_est, "q_est"), quat.as_quat(q_ref, "q_ref")
    movement = np.asarray(movement, bool)
    if not (q_est.shape == q_ref.shape and q_est.ndim == 2 and movement.shape == q_est.shape[:1]):
        raise ValueError(f"shape mismatch: q_est {q_est.shape}, q_ref {q_ref.shape}, movement {movement.shape}")
    return ErrorReference(q_ref, movement).errors(q_est, six_d)


def group_means(per_trial: dict[str, dict[str, float]], groups: dict[str, list[str]]) -> dict[str, dict]:
    """Mean of each metric over the trials of each group that are present in ``per_trial``.

    Returns group -> {metric: mean, ..., "n_trials": k, "n_listed": m}; groups with no present
    trial are left out (BROAD averages over a group's trials; here over those that were run).
    """
    out = {}
    for g, members in groups.items():
        present = [t for t in members if t in per_trial]
        if not present:
            continue
        metrics = per_trial[present[0]].keys()
        row = {m: float(np.mean([per_trial[t][m] for t in present])) for m in metrics}
        row.update(n_trials=len(present), n_listed=len(members))
        out[g] = row
    return out


@dataclass
class TagpResult:
    """TAGP of a grid: the parameter set with the lowest mean total RMSE over the trials.

    Attributes:
        params: the TAGP parameter dict.
        index: its index into the grid axes.
        mean_total: ``(len(axis0), len(axis1), ...)`` mean total RMSE over trials for the grid.
        per_trial: trial -> metrics at the TAGP.
    """

    params: dict
    index: tuple
    mean_total: np.ndarray
    per_trial: dict


def tagp(grid: dict[str, list], results: dict[tuple, dict[str, dict[str, float]]]) -> TagpResult:
    """BROAD's TAGP from grid results.

    Args:
        grid: parameter name -> list of values (axis order).
        results: tuple of parameter values (in ``grid`` order) -> trial -> metrics.
            Every grid point must cover the same trials.
    """
    names = list(grid)
    shape = tuple(len(v) for v in grid.values())
    mean_total = np.full(shape, np.nan)
    trial_sets = set()
    for idx in itertools.product(*(range(n) for n in shape)):
        key = tuple(grid[n][i] for n, i in zip(names, idx))
        if key not in results:
            raise KeyError(f"grid point {dict(zip(names, key))} has no results")
        per_trial = results[key]
        trial_sets.add(frozenset(per_trial))
        mean_total[idx] = np.mean([m["total"] for m in per_trial.values()])
    if len(trial_sets) != 1:
        raise ValueError("grid points were evaluated on different trial sets; TAGP needs one set")
    if np.all(np.isnan(mean_total)):
        raise ValueError("every grid point has NaN error")
    best = tuple(int(i) for i in np.unravel_index(np.nanargmin(mean_total), shape))
    params = {n: grid[n][i] for n, i in zip(names, best)}
    return TagpResult(params, best, mean_total, results[tuple(params.values())])
