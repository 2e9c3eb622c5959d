"""Training targets from BROAD's optical ground truth.

Everything here may look into the future (targets are computed offline, centred filters are
fine); only the *features* (``features.py``) must be causal.

Pipeline for one trial (``make_targets``):

1. ``bridge_gaps``: the reference orientation ``opt_quat`` with NaN runs of at most
   ``max_gap_s`` (0.1 s) bridged by SLERP between the valid neighbours; longer runs and runs
   touching the trial's ends stay NaN and are masked (``valid`` False).
2. ``angular_velocity``: true body rate (sensor frame) ``ω_k = log(q_{k-1}* ⊗ q_k) · fs``, the
   same convention as the gyro of ``simulate.imu_from_orientation`` (rate from k-1 to k), then
   an optional centred moving average of ``smooth_s`` seconds.
3. ``linear_acceleration``: second derivative of ``opt_pos`` (Savitzky–Golay, window
   ``savgol_s``, cubic) in the earth frame, rotated into the sensor frame with ``R_trueᵀ``.
   A trial without ``opt_pos`` (``Trial.opt_pos`` None, or no finite row): labels from the reference
   orientation alone, ``linear_acceleration_from_imu``: the centred ``savgol_s`` moving mean of
   ``a_meas − R_trueᵀ g`` (the specific force the IMU measures beyond gravity, smoothed as the optical
   derivative is). Step 6 then has no independent acceleration to check against: every valid sample
   is an inlier (``Targets.lin_acc_source`` says which source was used).
4. ``noise_targets``: ``η_a = a_meas − R_trueᵀ g`` with ``g = [0, 0, 9.81]`` (ENU) and
   ``η_m = m_meas − R_trueᵀ m_ref``; ``m_ref`` is the median of the earth-frame field
   ``R_true m_meas`` over static valid samples (``estimate_mag_ref``).
5. ``motion_state``: integer labels, ``STATE_NAMES[label]``:

   * ``0 rest``: ``|ω| < rest_gyr`` (0.2 rad/s) and ``|a_lin| < rest_acc`` (0.5 m/s²);
   * ``1 rotation``: not rest, ``|a_lin| < linacc_acc`` (1.5 m/s²);
   * ``2 linear_acceleration``: ``|a_lin| ≥ linacc_acc``;
   * ``3 vibration`` (tapping / vibration): the high-frequency part of the difference between
     the specific force the IMU measures and the one the optical truth predicts,
     ``r = a_meas − R_trueᵀ(g + a_lin)`` minus its centred ``vib_highpass_s`` (0.2 s) moving
     mean, has a centred moving RMS over ``vib_window_s`` (0.05 s) ``≥ vib_acc`` (2.0 m/s²);
     overrides the other states. (The optical truth is smooth, so this is vibration the
     IMU feels and the markers do not.)

   ``|ω|`` and ``|a_lin|`` are the smoothed ground-truth values of steps 2 and 3. The binary
   label set (``label_set="static_dynamic"``) is ``0 static`` = rest, ``1 dynamic`` = the rest.
6. ``ransac_inliers``: per trial, RANSAC fit of ``lowpass(a_meas) ≈ A · R_trueᵀ(g + a_lin) + b``
   (``lowpass`` a centred ``ransac_lowpass_s`` = 0.1 s moving mean, so that vibration and taps,
   which the noise model is meant to learn, are not taken for ground-truth errors)
   (``sklearn.linear_model.RANSACRegressor``, fixed ``random_state``); samples whose residual
   norm exceeds ``ransac_threshold`` m/s² are outliers (optical glitches, misalignment,
   synchronisation slips) and are dropped from the training targets when ``ransac`` is on.
"""
from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np
from scipy.signal import savgol_filter

from togglecf.core import quaternion as quat
from togglecf.core.extras import require
from togglecf.core.io import check_keys
from togglecf.data.broad import GRAVITY, Trial

__all__ = [
    "STATE_NAMES", "BINARY_NAMES", "LabelSettings", "Targets", "bridge_gaps", "angular_velocity",
    "linear_acceleration", "linear_acceleration_from_imu", "estimate_mag_ref", "noise_targets", "motion_state",
    "ransac_inliers", "make_targets", "state_names",
]

STATE_NAMES = ("rest", "rotation", "linear_acceleration", "vibration")
BINARY_NAMES = ("static", "dynamic")
G_ENU = np.array([0.0, 0.0, GRAVITY])


def state_names(label_set: str) -> tuple[str, ...]:
    if label_set == "state4":
        return STATE_NAMES
    if label_set == "static_dynamic":
        return BINARY_NAMES
    raise ValueError(f"unknown label_set {label_set!r}; expected 'state4' or 'static_dynamic'")


@dataclass(frozen=True)
class LabelSettings:
    """Target settings (see the module docstring; times in s, rates in rad/s, acc in m/s²)."""

    max_gap_s: float = 0.1
    smooth_s: float = 0.05
    savgol_s: float = 0.1
    rest_gyr: float = 0.2
    rest_acc: float = 0.5
    linacc_acc: float = 1.5
    vib_acc: float = 2.0
    vib_window_s: float = 0.05
    vib_highpass_s: float = 0.2
    ransac_lowpass_s: float = 0.1
    label_set: str = "state4"
    ransac: bool = True
    ransac_threshold: float = 2.0
    ransac_max_trials: int = 50
    ransac_max_samples: int = 20000
    seed: int = 0

    def __post_init__(self):
        state_names(self.label_set)
        for name in ("max_gap_s", "savgol_s", "rest_gyr", "rest_acc", "linacc_acc", "vib_acc",
                     "vib_window_s", "vib_highpass_s", "ransac_lowpass_s", "ransac_threshold"):
            if not getattr(self, name) > 0:
                raise ValueError(f"LabelSettings.{name} must be > 0, got {getattr(self, name)}")
        if self.smooth_s < 0:
            raise ValueError(f"LabelSettings.smooth_s must be >= 0, got {self.smooth_s}")

    @classmethod
    def from_dict(cls, d: dict) -> "LabelSettings":
        return cls(**check_keys(cls, d, "label"))

    def to_dict(self) -> dict:
        return asdict(self)


@dataclass
class Targets:
    """Per-sample targets of one trial (N samples)."""

    q_ref: np.ndarray        # (N, 4) bridged reference, NaN where masked
    valid: np.ndarray        # (N,) bool: reference and all targets defined
    omega: np.ndarray        # (N, 3) true angular velocity, sensor frame [rad/s]
    lin_acc: np.ndarray      # (N, 3) true linear acceleration, sensor frame [m/s²]
    eta_acc: np.ndarray      # (N, 3) accelerometer noise target [m/s²]
    eta_mag: np.ndarray      # (N, 3) magnetometer noise target [µT]
    state: np.ndarray        # (N,) int labels (-1 where invalid)
    inlier: np.ndarray       # (N,) bool RANSAC inliers (all valid samples when RANSAC fails)
    mag_ref: np.ndarray      # (3,) earth-frame field [µT]
    inlier_fraction: float   # inliers / valid samples
    state_names: tuple
    lin_acc_source: str = "opt_pos"  # "opt_pos", or "imu" (no optical position: linear_acceleration_from_imu)

    @property
    def train_mask(self) -> np.ndarray:
        """Samples usable as training targets (valid, and RANSAC inlier)."""
        return self.valid & self.inlier


# --------------------------------------------------------------------------------------- helpers

def _runs(mask: np.ndarray):
    """Start (inclusive) and stop (exclusive) indices of the True runs of a 1-D bool array."""
    d = np.diff(np.concatenate([[0], mask.astype(np.int8), [0]]))
    return np.flatnonzero(d == 1), np.flatnonzero(d == -1)


def _centred_mean(x: np.ndarray, width: int) -> np.ndarray:
    """Centred moving mean over ``width`` samples along axis 0; NaN if any input in the window is
    NaN or the window leaves the array."""
    if width <= 1:
        return x.copy()
    x = np.asarray(x, float)
    n = x.shape[0]
    bad = ~np.isfinite(x)
    xs = np.where(bad, 0.0, x)
    c = np.concatenate([np.zeros((1,) + x.shape[1:]), np.cumsum(xs, axis=0)])
    cb = np.concatenate([np.zeros((1,) + x.shape[1:]), np.cumsum(bad, axis=0)])
    half = width // 2
    lo = np.arange(n) - half
    hi = lo + width
    ok = (lo >= 0) & (hi <= n)
    lo_c, hi_c = np.clip(lo, 0, n), np.clip(hi, 0, n)
    out = (c[hi_c] - c[lo_c]) / width
    nbad = cb[hi_c] - cb[lo_c]
    ok = ok.reshape((n,) + (1,) * (x.ndim - 1)) & (nbad == 0)
    return np.where(ok, out, np.nan)


def _dilate(mask: np.ndarray, half: int) -> np.ndarray:
    """``out[k]`` True if ``mask`` is True anywhere in ``[k-half, k+half]``."""
    if half <= 0:
        return mask.copy()
    from scipy.ndimage import maximum_filter1d

    return maximum_filter1d(mask.astype(np.uint8), 2 * half + 1, mode="constant", cval=0).astype(bool)


# ----------------------------------------------------------------------------------------- steps

def bridge_gaps(q, fs: float, max_gap_s: float = 0.1):
    """Bridge NaN runs of at most ``max_gap_s`` seconds by SLERP between the valid neighbours.

    Returns ``(q_ref, valid)``: ``q_ref`` is ``(N, 4)`` with the bridged samples filled and the
    other NaN rows left NaN, ``valid`` marks the finite rows. Runs that touch the start or end of
    the trial have only one neighbour and are never bridged.
    """
    q = quat.as_quat(q).copy()
    n = q.shape[0]
    nan = ~np.all(np.isfinite(q), axis=1)
    max_len = int(np.floor(max_gap_s * fs + 1e-9))
    for s, e in zip(*_runs(nan)):
        if s == 0 or e == n or (e - s) > max_len:
            continue
        t = (np.arange(s, e) - (s - 1)) / (e - (s - 1))
        q[s:e] = quat.slerp(q[s - 1], q[e], t)
    return q, np.all(np.isfinite(q), axis=1)


def angular_velocity(q_ref, fs: float, smooth_s: float = 0.0) -> np.ndarray:
    """Body-frame angular velocity [rad/s] from orientations (sensor -> earth) ``(N, 4)``.

    ``ω_k = log(q_{k-1}* ⊗ q_k) · fs`` (``ω_0`` NaN), then a centred moving mean of
    ``round(smooth_s·fs)`` samples (forced odd) when ``smooth_s > 0``. NaN wherever a
    quaternion that enters the value is NaN.
    """
    q = quat.as_quat(q_ref)
    w = np.full((q.shape[0], 3), np.nan)
    if q.shape[0] > 1:
        dq = quat.multiply(quat.conjugate(q[:-1]), q[1:])
        w[1:] = quat.to_rotvec(dq) * fs
    width = int(round(smooth_s * fs)) | 1 if smooth_s > 0 else 1
    return _centred_mean(w, width)


def linear_acceleration(pos, q_ref, fs: float, savgol_s: float = 0.1, max_gap_s: float = 0.1):
    """True linear acceleration in the sensor frame [m/s²] ``(N, 3)``.

    ``opt_pos`` NaN runs of at most ``max_gap_s`` are linearly interpolated; the cubic
    Savitzky–Golay second derivative (window ``round(savgol_s·fs)`` samples, forced odd, ≥ 5)
    gives the earth-frame acceleration, which ``R_trueᵀ`` rotates into the sensor frame.
    Samples within half a window of a longer position gap, or with no reference orientation,
    are NaN.
    """
    pos = np.asarray(pos, float)
    n = pos.shape[0]
    nan = ~np.all(np.isfinite(pos), axis=1)
    width = max(5, int(round(savgol_s * fs)) | 1)
    if nan.all() or n < width:
        return np.full((n, 3), np.nan)
    t = np.arange(n)
    filled = np.empty_like(pos)
    for i in range(3):
        filled[:, i] = np.interp(t, t[~nan], pos[~nan, i])
    long_gap = np.zeros(n, bool)
    max_len = int(np.floor(max_gap_s * fs + 1e-9))
    for s, e in zip(*_runs(nan)):
        if s == 0 or e == n or (e - s) > max_len:
            long_gap[s:e] = True
    a_earth = savgol_filter(filled, width, 3, deriv=2, delta=1.0 / fs, axis=0, mode="interp")
    a_earth[_dilate(long_gap, width // 2)] = np.nan
    return quat.rotate(quat.conjugate(q_ref), a_earth)


def estimate_mag_ref(mag, q_ref, mask) -> np.ndarray:
    """Earth-frame field [µT]: per-axis median of ``R_true m_meas`` over ``mask`` samples (the
    static valid ones); all valid samples when fewer than 100 are static."""
    m_earth = quat.rotate(q_ref, mag)
    fin = np.all(np.isfinite(m_earth), axis=1)
    sel = mask & fin
    if sel.sum() < 100:
        sel = fin
    if not sel.any():
        return np.full(3, np.nan)
    return np.median(m_earth[sel], axis=0)


def noise_targets(acc, mag, q_ref, mag_ref):
    """``η_a = a_meas − R_trueᵀ g`` and ``η_m = m_meas − R_trueᵀ m_ref`` (sensor frame, (N, 3))."""
    eta_m = np.asarray(mag, float) - quat.rotate(quat.conjugate(q_ref), np.asarray(mag_ref, float))
    return _beyond_gravity(acc, q_ref), eta_m


def _beyond_gravity(acc, q_ref) -> np.ndarray:
    """``a_meas − R_trueᵀ g`` (sensor frame, (N, 3)): η_a, and the linear acceleration before smoothing."""
    return np.asarray(acc, float) - quat.rotate(quat.conjugate(q_ref), G_ENU)


def linear_acceleration_from_imu(acc, q_ref, fs: float, savgol_s: float = 0.1) -> np.ndarray:
    """Linear acceleration in the sensor frame [m/s²] ``(N, 3)`` without an optical position: the centred
    moving mean (window ``round(savgol_s·fs)`` samples, forced odd) of ``a_meas − R_trueᵀ g``. It carries the
    accelerometer's own errors and the reference's tilt errors (2° of tilt: 0.34 m/s²), which the optical
    derivative does not; NaN where the reference orientation is."""
    return _centred_mean(_beyond_gravity(acc, q_ref), max(1, int(round(savgol_s * fs)) | 1))


def motion_state(omega, lin_acc, acc, q_ref, fs: float, s: LabelSettings) -> np.ndarray:
    """Integer motion state per sample (see the module docstring); -1 where undefined."""
    w = np.linalg.norm(omega, axis=1)
    a = np.linalg.norm(lin_acc, axis=1)
    f_pred = quat.rotate(quat.conjugate(q_ref), G_ENU + quat.rotate(q_ref, lin_acc))
    r = np.asarray(acc, float) - f_pred
    r_hp = r - _centred_mean(r, max(3, int(round(s.vib_highpass_s * fs)) | 1))
    vib_width = max(1, int(round(s.vib_window_s * fs)) | 1)
    vib_rms = np.sqrt(_centred_mean(np.sum(r_hp ** 2, axis=1)[:, None], vib_width)[:, 0])
    defined = np.isfinite(w) & np.isfinite(a) & np.isfinite(vib_rms)
    state = np.full(w.shape, -1, dtype=np.int64)
    state[defined] = 1
    state[defined & (w < s.rest_gyr) & (a < s.rest_acc)] = 0
    state[defined & (a >= s.linacc_acc)] = 2
    state[defined & (vib_rms >= s.vib_acc)] = 3
    if s.label_set == "static_dynamic":
        state = np.where(state < 0, -1, (state != 0).astype(np.int64))
    return state


def ransac_inliers(acc, predicted, valid, threshold: float, seed: int = 0, max_trials: int = 50,
                   max_samples: int = 20000):
    """RANSAC fit ``acc ≈ A · predicted + b`` (3x3 A, 3-vector b) over the ``valid`` samples.

    The fit uses at most ``max_samples`` evenly spaced valid samples (for speed); the winning
    affine model is then applied to every valid sample and those with residual norm
    ``> threshold`` are outliers. Returns ``(inlier (N,) bool, fraction of valid samples,
    (A, b))``. Deterministic for a given ``seed``.
    """
    linear_model = require("sklearn.linear_model", extra="train", what="computing the RANSAC-cleaned training targets")
    LinearRegression, RANSACRegressor = linear_model.LinearRegression, linear_model.RANSACRegressor

    acc = np.asarray(acc, float)
    predicted = np.asarray(predicted, float)
    ok = valid & np.all(np.isfinite(predicted), axis=1) & np.all(np.isfinite(acc), axis=1)
    inlier = np.zeros(acc.shape[0], bool)
    idx = np.flatnonzero(ok)
    if idx.size < 50:
        inlier[idx] = True
        return inlier, 1.0 if idx.size else 0.0, (np.eye(3), np.zeros(3))
    fit_idx = idx[np.linspace(0, idx.size - 1, min(max_samples, idx.size)).astype(np.int64)]
    model = RANSACRegressor(
        LinearRegression(), min_samples=20, residual_threshold=threshold, max_trials=max_trials,
        loss=lambda y, yp: np.linalg.norm(y - yp, axis=1), random_state=seed)
    model.fit(predicted[fit_idx], acc[fit_idx])
    est = model.estimator_
    A, b = np.asarray(est.coef_), np.asarray(est.intercept_)
    resid = np.linalg.norm(acc[idx] - (predicted[idx] @ A.T + b), axis=1)
    inlier[idx] = resid <= threshold
    return inlier, float(inlier[idx].mean()), (A, b)


def make_targets(trial: Trial, settings: LabelSettings | None = None) -> Targets:
    """All targets of one trial (see the module docstring)."""
    s = settings or LabelSettings()
    fs = trial.fs
    q_ref, q_valid = bridge_gaps(trial.opt_quat, fs, s.max_gap_s)
    omega = angular_velocity(q_ref, fs, s.smooth_s)
    optical = trial.opt_pos is not None and bool(np.isfinite(trial.opt_pos).all(axis=1).any())
    lin_acc = (linear_acceleration(trial.opt_pos, q_ref, fs, s.savgol_s, s.max_gap_s) if optical
               else linear_acceleration_from_imu(trial.acc, q_ref, fs, s.savgol_s))
    state = motion_state(omega, lin_acc, trial.acc, q_ref, fs, s)
    valid = q_valid & (state >= 0)
    rest = valid & (state == 0) if s.label_set == "state4" else valid & (state == 0)
    mag_ref = estimate_mag_ref(trial.mag, q_ref, rest)
    eta_a, eta_m = noise_targets(trial.acc, trial.mag, q_ref, mag_ref)
    f_pred = quat.rotate(quat.conjugate(q_ref), G_ENU + quat.rotate(q_ref, lin_acc))
    acc_lp = _centred_mean(trial.acc, max(1, int(round(s.ransac_lowpass_s * fs)) | 1))
    inlier, frac, _ = ransac_inliers(acc_lp, f_pred, valid, s.ransac_threshold, s.seed,
                                     s.ransac_max_trials, s.ransac_max_samples)
    for arr in (eta_a, eta_m, omega, lin_acc):
        arr[~valid] = np.nan
    return Targets(q_ref=q_ref, valid=valid, omega=omega, lin_acc=lin_acc, eta_acc=eta_a, eta_mag=eta_m,
                   state=np.where(valid, state, -1), inlier=inlier, mag_ref=mag_ref, inlier_fraction=frac,
                   state_names=state_names(s.label_set), lin_acc_source="opt_pos" if optical else "imu")
