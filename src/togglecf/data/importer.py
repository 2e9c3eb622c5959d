"""Your recordings in BROAD's layout: ``togglecf import`` (``import_recording``).

A CSV or NumPy log with time stamps, in any of the usual units, becomes one HDF5 trial in BROAD's
layout plus its entry in the directory's ``trials.json``, so that ``togglecf evaluate --data DIR``
runs on it. Everything is converted at the boundary: units to rad/s, m/s², µT, time to seconds,
quaternions to ``[w, x, y, z]`` sensor -> ENU. The time stamps are kept (``imu_time`` [s],
``Trial.time``); ``sampling_rate`` is their median rate.

The inputs (``docs/guide/import.md`` has examples):

* IMU log, CSV with a header row: ``t``, ``gyr_x gyr_y gyr_z``, ``acc_x acc_y acc_z``,
  ``mag_x mag_y mag_z``; optional ``q0 q1 q2 q3`` (a reference already on the IMU's clock and
  axes, in ``quat_order``; or ``qw qx qy qz`` by name), ``pos_x pos_y pos_z`` [m] and ``movement``
  (0/1). ``.npz``: keys ``t`` ``(N,)``, ``gyr``/``acc``/``mag`` ``(N, 3)``, optional ``quat``
  ``(N, 4)``, ``pos`` ``(N, 3)``, ``movement`` ``(N,)``. ``.npy``: one ``(N, 10)`` array
  ``t, gyr, acc, mag`` (the live stream's line order) or ``(N, 14)`` with ``q0..q3`` after them.
* Reference log (``reference=``, a mocap recording on its own clock and marker axes): ``t``,
  ``q0 q1 q2 q3`` (or ``qw qx qy qz``), optional ``pos_x pos_y pos_z`` [m]; ``.npz`` keys ``t``,
  ``quat``, ``pos``; ``.npy`` ``(M, 5)`` or ``(M, 8)``. NaN (or empty) rows where markers were lost.

With a reference log, it is synchronised and aligned the way BROAD was made, with the BROAD authors'
toolbox qmt (the ``[import]`` extra; Laidig et al., Data 6(7):72, 2021, appendices B and C):
resampled onto the IMU's time stamps (SLERP), ``qmt.syncOptImu`` (clock offset and drift from the
angular rates), resampled again on the corrected clock, optionally ``qmt.calibrateMagnetometerSimple``
(hard and soft iron), then ``qmt.alignOptImu`` (IMU-to-marker rotation, tilt and heading of the
reference frame): ``opt_quat = qEOpt2EImu ⊗ q_ref ⊗ qImu2Seg``. The residuals are reported.

``movement`` is BROAD's rule (``broad_movement``) unless the log has a ``movement`` column.
"""
from __future__ import annotations

import contextlib
import dataclasses
import io
import json
import os
from pathlib import Path

import numpy as np
import scipy.signal

from togglecf.core import quaternion as quat
from togglecf.core.extras import MissingExtraError, check_extra, deferred, require
from togglecf.core.io import atomic_write_json
from togglecf.core.units import TIME_UNITS, parse_units
from togglecf.data.broad import DataError, Trial, checked_time_stamps, min_samples, write_broad_hdf5

__all__ = ["ImportSettings", "ImportResult", "ImuLog", "ReferenceLog", "import_recording", "read_imu_log",
           "read_reference_log", "align_reference", "broad_movement", "add_to_index", "summary_text",
           "plot_residuals", "QUAT_ORDERS", "FRAMES", "IMU_COLUMNS", "REFERENCE_COLUMNS"]

#: qmt (the ``import`` extra), imported on first use: an import without a reference never touches it
qmt = deferred("qmt", extra="import", what="togglecf import --reference")
REFERENCE_WHAT = "togglecf import --reference"

QUAT_ORDERS = ("wxyz", "xyzw")
FRAMES = ("enu", "ned")
_XYZ = ("x", "y", "z")
#: the IMU log's columns, in the ``.npy`` order (``q0..q3`` optional)
IMU_COLUMNS = ("t", *(f"{s}_{a}" for s in ("gyr", "acc", "mag") for a in _XYZ))
_QUAT_COLUMNS = ("q0", "q1", "q2", "q3")
_QUAT_BY_NAME = ("qw", "qx", "qy", "qz")
_POS_COLUMNS = tuple(f"pos_{a}" for a in _XYZ)
#: the reference log's columns, in the ``.npy`` order (``pos_*`` optional)
REFERENCE_COLUMNS = ("t", *_QUAT_COLUMNS, *_POS_COLUMNS)
#: ``.npz`` key -> the columns it holds
_NPZ_KEYS = {"t": ("t",), "gyr": IMU_COLUMNS[1:4], "acc": IMU_COLUMNS[4:7], "mag": IMU_COLUMNS[7:10],
             "quat": _QUAT_COLUMNS, "pos": _POS_COLUMNS, "movement": ("movement",)}


@dataclasses.dataclass(frozen=True)
class ImportSettings:
    """How ``import_recording`` reads and aligns a recording.

    Attributes:
        units: the logs' units, ``"gyr=dps,acc=g,mag=uT"`` (any subset; default rad/s, m/s², µT;
            ``togglecf.core.units``: gyr rad/s|dps, acc m/s2|g|mg, mag uT|gauss|G|mT|nT|mG).
        time_unit: unit of the ``t`` columns of both logs: ``s``, ``ms`` or ``us``.
        frame: earth frame of the reference quaternions and positions, ``enu`` or ``ned``
            (converted to ENU). The IMU's own axes are kept as they are: the alignment finds the
            IMU-to-marker rotation whatever they are.
        quat_order: order of ``q0..q3`` (and of an ``.npz``'s ``quat``): ``wxyz`` or ``xyzw``.
        calibrate_mag: estimate and remove hard and soft iron (``qmt.calibrateMagnetometerSimple``;
            needs a reference log, i.e. the ``import`` extra). Best on a recording of slow rotations
            in all directions away from iron.
        mag_norm_ut: field strength [µT] the calibrated magnetometer is scaled to; ``None``: the
            median norm of the uncalibrated one (the unit stays what the log said).
        thorough: qmt's full searches, as BROAD was made: ``syncOptImu`` from 49 start points and
            ``alignOptImu`` from 24 (every axis-aligned mounting), for an IMU mounted at an unknown
            angle to the markers. Default ``False``: qmt's ``fast`` (one start each, from a
            cross-correlated offset and the identity mounting): seconds instead of many minutes,
            and enough for a mounting within some tens of degrees of the markers' axes.
        rest_threshold: BROAD's movement rule: rotation rate [rad/s] (after its low-pass filters)
            under which a sample is at rest.
        min_rest_s: rests longer than this [s] are not scored.
        rest_margin_s: an inner rest is shortened by this much [s] at each end (the movement
            around it stays scored).
    """

    units: str | None = None
    time_unit: str = "s"
    frame: str = "enu"
    quat_order: str = "wxyz"
    calibrate_mag: bool = False
    mag_norm_ut: float | None = None
    thorough: bool = False
    rest_threshold: float = 0.3
    min_rest_s: float = 5.0
    rest_margin_s: float = 0.5

    def __post_init__(self):
        parse_units(self.units)  # an unknown unit fails here, before any file is read
        for name, value, known in (("time_unit", self.time_unit, tuple(TIME_UNITS)), ("frame", self.frame, FRAMES),
                                   ("quat_order", self.quat_order, QUAT_ORDERS)):
            if value not in known:
                raise ValueError(f"--{name.replace('_', '-')}: unknown value {value!r} (one of {', '.join(known)})")


@dataclasses.dataclass(frozen=True)
class ImuLog:
    """An IMU log converted to the package's units (N samples): ``time (N,)`` [s], ``gyr``, ``acc``,
    ``mag`` ``(N, 3)`` [rad/s, m/s², µT]; ``quat (N, 4)`` sensor -> ENU, ``pos (N, 3)`` [m, ENU] and
    ``movement (N,)`` bool when the log has them, else ``None``."""

    source: Path
    time: np.ndarray
    gyr: np.ndarray
    acc: np.ndarray
    mag: np.ndarray
    quat: np.ndarray | None = None
    pos: np.ndarray | None = None
    movement: np.ndarray | None = None

    @property
    def fs(self) -> float:
        """Nominal sampling rate [Hz]: the median rate of the time stamps."""
        return float(1.0 / np.median(np.diff(self.time)))


@dataclasses.dataclass(frozen=True)
class ReferenceLog:
    """A reference (mocap) log on its own clock (M samples): ``time (M,)`` [s], ``quat (M, 4)``
    marker -> reference earth frame converted to ENU (NaN rows where lost), ``pos (M, 3)`` [m] or ``None``."""

    source: Path
    time: np.ndarray
    quat: np.ndarray
    pos: np.ndarray | None = None


@dataclasses.dataclass
class ImportResult:
    """What ``import_recording`` wrote: the trial, its HDF5 file, the report (also saved as
    ``<name>.import.json``; ``summary_text`` prints it) and the residual plot (``None`` without a
    reference or without matplotlib)."""

    trial: Trial
    path: Path
    report: dict
    plot: Path | None = None
    files: list = dataclasses.field(default_factory=list)


# ------------------------------------------------------------------------------------------ reading

def _read_columns(path: Path, npy_columns: tuple) -> dict:
    """Column name (lower case) -> ``(N,)`` float64 from a CSV (header row), ``.npz`` or ``.npy``."""
    if not path.is_file():
        raise DataError(path, None, "file not found")
    suffix = path.suffix.lower()
    try:
        if suffix == ".npz":
            with np.load(path) as z:
                return _npz_columns(path, {k.lower(): np.asarray(z[k], dtype=np.float64) for k in z.files})
        if suffix == ".npy":
            return _npy_columns(path, np.asarray(np.load(path), dtype=np.float64), npy_columns)
        with open(path, encoding="utf-8-sig") as f:
            header = [h.strip().lower() for h in f.readline().strip().split(",")]
            rows = np.genfromtxt(f, delimiter=",", dtype=np.float64, ndmin=2)
    except (OSError, ValueError, TypeError) as exc:  # unreadable, ragged rows, text where numbers belong
        raise DataError(path, None, f"cannot read it as {suffix.lstrip('.') or 'CSV'}: {exc}".replace("\n", " ")) \
            from None
    if len(set(header)) != len(header):
        raise DataError(path, None, f"a column name appears twice in the header {header}")
    if rows.shape[1] != len(header) and rows.size:
        raise DataError(path, None, f"the header names {len(header)} columns, the rows have {rows.shape[1]}")
    return {h: rows[:, i] for i, h in enumerate(header)}


def _npz_columns(path, arrays: dict) -> dict:
    out = {}
    for key, arr in arrays.items():
        names = _NPZ_KEYS.get(key, (key,))
        arr = arr.reshape(-1, 1) if arr.ndim == 1 else arr
        if arr.ndim != 2 or arr.shape[1] != len(names):
            raise DataError(path, key, f"expected shape (N,{'' if len(names) == 1 else ' ' + str(len(names))}), "
                                       f"got {arr.shape}")
        out.update({n: arr[:, i] for i, n in enumerate(names)})
    return out


def _npy_columns(path, arr, names: tuple) -> dict:
    widths = {len(names) - 3, len(names)} if names == REFERENCE_COLUMNS else {len(names), len(names) + 4}
    if arr.ndim != 2 or arr.shape[1] not in widths:
        optional = ", q0..q3" if names == IMU_COLUMNS else ""
        raise DataError(path, None, f"expected a 2-D array with {' or '.join(map(str, sorted(widths)))} columns "
                                    f"({', '.join(names)}{optional}), got {arr.shape}")
    cols = names + (_QUAT_COLUMNS if names == IMU_COLUMNS else ())
    return {n: arr[:, i] for i, n in enumerate(cols[:arr.shape[1]])}


def _column(path, cols: dict, name: str, required: bool = True) -> np.ndarray | None:
    if name not in cols:
        if not required:
            return None
        raise DataError(path, name, f"missing column (the file has: {', '.join(cols) or 'none'})")
    if not np.isfinite(cols[name]).any():
        raise DataError(path, name, "no finite value (empty or NaN in every row)")
    return cols[name]


def _vector(path, cols: dict, names, required: bool = True) -> np.ndarray | None:
    """The columns ``names`` stacked ``(N, len(names))``; ``None`` when none is there and not ``required``."""
    if not required and not any(n in cols for n in names):
        return None
    return np.stack([_column(path, cols, n) for n in names], axis=1)


def _time(path, cols: dict, settings: ImportSettings) -> np.ndarray:
    return checked_time_stamps(path, "t", _column(path, cols, "t"), settings.time_unit, TIME_UNITS[settings.time_unit])


def _quaternions(path, cols: dict, settings: ImportSettings) -> np.ndarray | None:
    """``(N, 4)`` sensor -> ENU from ``qw..qz`` or ``q0..q3`` (``quat_order``), or ``None``; rows
    with any NaN become all-NaN (markers lost)."""
    if all(n in cols for n in _QUAT_BY_NAME):
        q = _vector(path, cols, _QUAT_BY_NAME)
    else:
        q = _vector(path, cols, _QUAT_COLUMNS, required=False)
        if q is not None and settings.quat_order == "xyzw":
            q = q[:, [3, 0, 1, 2]]
    if q is None:
        return None
    norm = np.linalg.norm(q, axis=1)
    lost = ~np.isfinite(norm) | (norm < 1e-9)
    bad = ~lost & (np.abs(norm - 1.0) > 1e-2)
    if bad.any():
        raise DataError(path, "q0", f"row {int(np.argmax(bad))}: quaternion norm {norm[bad][0]:.4g}, expected 1 "
                                    f"(is --quat-order {settings.quat_order} right?)")
    q = np.where(lost[:, None], np.nan, q / np.where(lost, 1.0, norm)[:, None])
    return quat.from_frame(q, settings.frame)


def _positions(path, cols: dict, settings: ImportSettings) -> np.ndarray | None:
    pos = _vector(path, cols, _POS_COLUMNS, required=False)
    return None if pos is None else quat.rotate(quat.from_frame(quat.IDENTITY, settings.frame), pos)


def read_imu_log(path, settings: ImportSettings = ImportSettings()) -> ImuLog:
    """Read and convert an IMU log (columns: module docstring). Raises ``DataError`` (one line naming
    the file, the column and the problem) for a missing or empty column, time stamps that do not
    increase, a non-unit quaternion, or fewer samples than a trial needs."""
    path = Path(path)
    cols = _read_columns(path, IMU_COLUMNS)
    t = _time(path, cols, settings)
    if t.size < 2 or t.size < min_samples(1.0 / np.median(np.diff(t))):
        raise DataError(path, "t", f"{t.size} rows: too short to evaluate a filter on (at least "
                                   "togglecf.data.broad.MIN_DURATION_S of samples)")
    k_gyr, k_acc, k_mag = parse_units(settings.units)
    mov = _column(path, cols, "movement", required=False)
    if mov is not None and not np.all(np.isin(mov, (0.0, 1.0))):
        raise DataError(path, "movement", "must be 0 or 1 in every row")
    return ImuLog(path, t, k_gyr * _vector(path, cols, IMU_COLUMNS[1:4]), k_acc * _vector(path, cols, IMU_COLUMNS[4:7]),
                  k_mag * _vector(path, cols, IMU_COLUMNS[7:10]), _quaternions(path, cols, settings),
                  _positions(path, cols, settings), None if mov is None else mov.astype(bool))


def read_reference_log(path, settings: ImportSettings = ImportSettings()) -> ReferenceLog:
    """Read and convert a reference (mocap) log (columns: module docstring); ``DataError`` as
    ``read_imu_log``."""
    path = Path(path)
    cols = _read_columns(path, REFERENCE_COLUMNS)
    t = _time(path, cols, settings)
    q = _quaternions(path, cols, settings)
    if q is None:
        raise DataError(path, "q0", f"missing column: a reference needs q0..q3 or qw..qz (the file has: "
                                    f"{', '.join(cols)})")
    return ReferenceLog(path, t, q, _positions(path, cols, settings))


# ----------------------------------------------------------------------- synchronisation, alignment

def _clock_line(t: np.ndarray) -> tuple[float, float]:
    """``(rate [Hz], c0 [s])`` of the straight line ``t_k ≈ c0 + k / rate`` through the stamps: the
    evenly spaced clock qmt assumes (it takes a rate, not stamps)."""
    slope, c0 = np.polyfit(np.arange(t.size, dtype=np.float64), t, 1)
    return float(1.0 / slope), float(c0)


def _reference_at(ref: ReferenceLog, t_ref: np.ndarray):
    """The reference at reference-clock times ``t_ref`` [s]: quaternions by SLERP, positions linearly
    (``qmt.quatInterp``/``vecInterp``); NaN outside its span and next to lost samples."""
    ind = np.interp(t_ref, ref.time, np.arange(ref.time.size, dtype=np.float64), left=-1.0,
                    right=float(ref.time.size))
    q = qmt.quatInterp(ref.quat, ind, extend=False)
    return q, None if ref.pos is None else qmt.vecInterp(ref.pos, ind, extend=False)


def _synchronise(imu: ImuLog, ref: ReferenceLog, settings: ImportSettings) -> dict:
    """Clock offset and drift between the logs by ``qmt.syncOptImu`` (the reference resampled onto the
    IMU's stamps as they are, then the angular rates matched). Returns ``offset_s`` (IMU stamp minus
    reference stamp of the same instant, at the first IMU sample), ``drift_ppm`` (how much faster the
    IMU's clock runs) and ``ref_time`` ``(N,)``: each IMU sample's instant on the reference clock [s]."""
    rate, c0 = _clock_line(imu.time)
    q_raw, _ = _reference_at(ref, imu.time)
    if np.isfinite(q_raw[:, 0]).sum() < min_samples(rate):
        raise DataError(ref.source, "t", f"the reference's stamps ({ref.time[0]:.3f} to {ref.time[-1]:.3f} s) "
                        f"hardly overlap the IMU's ({imu.time[0]:.3f} to {imu.time[-1]:.3f} s): the two logs must "
                        "be on roughly the same clock (within 15 % of the recording's length)")
    sync = qmt.SyncMapper(qmt.syncOptImu(q_raw, rate, imu.gyr, rate, dict(fast=not settings.thorough)))
    # opt index j (the reference at IMU stamp j) happened at IMU index a*j + b
    b = float(sync.map("opt", "ind", 0.0, "imu", "ind"))
    a = float(sync.map("opt", "ind", 1.0, "imu", "ind")) - b
    ref_time = c0 - b / (a * rate) + (imu.time - c0) / a
    return {"offset_s": float(imu.time[0] - ref_time[0]), "drift_ppm": (a - 1.0) * 1e6, "ref_time": ref_time}


def _calibrate_mag(imu: ImuLog, rate: float, settings: ImportSettings) -> tuple[np.ndarray, dict]:
    """``(mag (N, 3) [µT], report)``: hard and soft iron removed by ``qmt.calibrateMagnetometerSimple``
    (``gain * mag - bias``) when it succeeds; the magnetometer unchanged when it reports failure."""
    ok = np.isfinite(imu.gyr).all(1) & np.isfinite(imu.acc).all(1) & np.isfinite(imu.mag).all(1)
    norm = settings.mag_norm_ut or float(np.median(np.linalg.norm(imu.mag[ok], axis=1)))
    gain, bias, success = qmt.calibrateMagnetometerSimple(imu.gyr[ok], imu.acc[ok], imu.mag[ok], 1.0 / rate,
                                                          targetNorm=norm)
    report = {"calibrated": bool(success), "gain": gain, "bias_ut": bias, "norm_ut": norm}
    return (gain * imu.mag - bias if success else imu.mag), report


def align_reference(imu: ImuLog, ref: ReferenceLog, settings: ImportSettings = ImportSettings()):
    """Synchronise and align ``ref`` to ``imu`` with qmt (module docstring; the ``import`` extra).

    Returns ``(opt_quat (N, 4) sensor -> ENU, opt_pos (N, 3) [m] or None, mag (N, 3) [µT],
    calibrated when asked, report dict)``. The report holds the clock offset [s] and drift [ppm],
    ``imu_to_marker`` (qmt's ``qImu2Seg``) and ``reference_frame`` (``qEOpt2EImu``) with their angles
    [deg], the reference frame's tilt and heading [deg], the gyro and accelerometer biases, qmt's
    costs and the lines qmt printed (``warnings``)."""
    printed = io.StringIO()
    with contextlib.redirect_stdout(printed):  # qmt prints its warnings; they go into the report
        sync = _synchronise(imu, ref, settings)
        q_ref, pos_ref = _reference_at(ref, sync["ref_time"])
        rate, _ = _clock_line(imu.time)
        mag, mag_report = (_calibrate_mag(imu, rate, settings) if settings.calibrate_mag
                           else (imu.mag, {"calibrated": False}))
        alignment = qmt.alignOptImu(imu.gyr, imu.acc, mag, q_ref, pos_ref, rate, dict(fast=not settings.thorough))
    q_imu2seg, q_frame = np.asarray(alignment["qImu2Seg"]), np.asarray(alignment["qEOpt2EImu"])
    opt_quat = quat.multiply(quat.multiply(q_frame, q_ref), q_imu2seg)
    info = alignment["info"]
    report = {
        "clock_offset_s": sync["offset_s"], "clock_drift_ppm": sync["drift_ppm"],
        "imu_to_marker": q_imu2seg,
        "imu_to_marker_deg": float(np.degrees(quat.angle_between(q_imu2seg, quat.IDENTITY))),
        "reference_frame": q_frame, "reference_tilt_deg": float(alignment["qEOpt2EImu_6D_total_deg"]),
        "reference_heading_deg": float(np.degrees(quat.to_euler_zyx(q_frame)[2])),
        "gyr_bias": np.asarray(info["bias"][0]), "acc_bias": np.asarray(info["accbias"]), "gravity": float(info["g"]),
        "qmt_gyr_cost": float(info["gyr_cost"]), "qmt_acc_cost": float(info["acc_cost"]),
        "magnetometer": mag_report, "warnings": printed.getvalue().splitlines(),
    }
    return opt_quat, None if pos_ref is None else quat.rotate(q_frame, pos_ref), mag, report


def residuals(time: np.ndarray, gyr, acc, mag, opt_quat, report: dict) -> dict:
    """Per-sample residuals of the aligned reference ``(N,)``: ``gyr_dps`` = |gyro − bias − the
    reference's rotation rate| [°/s], ``acc`` = |acc − bias rotated to ENU − gravity| [m/s²] (includes
    any linear acceleration), ``heading_deg`` = the magnetometer's heading in the aligned frame
    (0: magnetic north along y) [°]. NaN where the reference is lost."""
    rate = np.zeros_like(gyr)
    rate[1:] = quat.to_rotvec(quat.multiply(quat.conjugate(opt_quat[:-1]), opt_quat[1:])) / np.diff(time)[:, None]
    rate[0] = np.nan
    up = np.array([0.0, 0.0, report["gravity"]])
    mag_enu = quat.rotate(opt_quat, mag)
    return {"gyr_dps": np.degrees(np.linalg.norm(gyr - report["gyr_bias"] - rate, axis=1)),
            "acc": np.linalg.norm(quat.rotate(opt_quat, acc - report["acc_bias"]) - up, axis=1),
            "heading_deg": np.degrees(np.arctan2(-mag_enu[:, 0], mag_enu[:, 1]))}


def _rms(x) -> float:
    x = np.asarray(x)
    x = x[np.isfinite(x)]
    return float(np.sqrt(np.mean(x ** 2))) if x.size else float("nan")


# ------------------------------------------------------------------------------------- movement

def broad_movement(gyr, fs: float, threshold: float = 0.3, min_rest_s: float = 5.0, margin_s: float = 0.5,
                   fc_rate: float = 10.0, fc_norm: float = 0.2) -> np.ndarray:
    """BROAD's movement mask ``(N,)`` bool from angular rates ``gyr (N, 3)`` [rad/s] at ``fs`` [Hz].

    The rule of the BROAD authors' toolbox (qmt's ``_detectMovement``, which made BROAD's
    ``movement``): each axis low-passed at ``fc_rate`` Hz, the norm low-passed at ``fc_norm`` Hz
    (2nd-order Butterworth, forwards and backwards); a sample is at rest below ``threshold`` rad/s;
    rests longer than ``min_rest_s`` are not movement, an inner one shortened by ``margin_s`` at each
    end. BROAD applied it to the optical rotation rate; here it is the gyroscope's (there with or
    without a reference; the same up to noise and bias, far below the 0.3 rad/s threshold).
    Non-finite samples are interpolated first."""
    g = np.array(gyr, dtype=np.float64)
    ok = np.isfinite(g).all(axis=1)
    k = np.arange(g.shape[0])
    g = np.stack([np.interp(k, k[ok], g[ok, i]) for i in range(3)], axis=1)
    if fc_rate < fs / 2:
        g = scipy.signal.filtfilt(*scipy.signal.butter(2, fc_rate / (fs / 2)), g, axis=0)
    norm = scipy.signal.filtfilt(*scipy.signal.butter(2, fc_norm / (fs / 2)), np.linalg.norm(g, axis=1))
    edges = np.diff(np.concatenate(([0], (norm < threshold).astype(int), [0])))
    movement = np.ones(g.shape[0], bool)
    margin = int(margin_s * fs)
    for start, stop in zip(np.flatnonzero(edges == 1), np.flatnonzero(edges == -1)):
        if stop - start > min_rest_s * fs:
            movement[start + (margin if start > 0 else 0):stop - (margin if stop < g.shape[0] else 0)] = False
    return movement


# ------------------------------------------------------------------------------------ writing

def add_to_index(root, name: str, description: str, groups=()) -> Path:
    """Add (or replace) trial ``name`` in ``root/trials.json`` (BROAD's format: ``trials`` name ->
    ``description``, ``groups``; ``groups`` a list of ``name``/``level``/``category``), creating the
    file and any new group; written atomically."""
    index_file = Path(root) / "trials.json"
    info = {"groups": [], "trials": {}}
    if index_file.is_file():
        try:
            info = json.loads(index_file.read_text())
            known = {g["name"] for g in info["groups"]}
            info["trials"] = dict(info["trials"])
        except (ValueError, KeyError, TypeError) as exc:
            raise DataError(index_file, None, f"not a BROAD trials.json: {exc}") from None
    else:
        known = set()
    info["trials"][name] = {"description": description, "groups": list(groups)}
    info["groups"] += [{"name": g, "level": 1, "category": "imported"} for g in dict.fromkeys(groups) if g not in known]
    return atomic_write_json(index_file, info)


def _write_trial(path: Path, trial: Trial, info: str) -> Path:
    """``write_broad_hdf5`` to a temporary file beside ``path``, then renamed over it: a reader never
    sees half a trial."""
    tmp = path.with_name(f".{path.name}.tmp")
    try:
        write_broad_hdf5(tmp, trial, info)
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    return path


def _units_hint(exc: DataError, settings: ImportSettings) -> DataError:
    """The trial's unit check (``Trial``) refers to the package's fields; from the importer it names
    the option that fixes it."""
    return DataError(exc.source, exc.field, f"{exc.problem} (the log's units: --units {settings.units or 'default'})")


def summary_text(report: dict) -> str:
    """A few lines: samples, rate, movement share and, with a reference, the clock, the alignment,
    the magnetometer and the residuals."""
    lines = [f"{report['name']}: {report['n_samples']} samples, {report['duration_s']:.1f} s, median rate "
             f"{report['sampling_rate']:.3f} Hz (time stamps kept: imu_time), movement {report['movement_share']:.0%} "
             f"({report['movement_from']})"]
    ref = report.get("reference")
    if not ref:
        lines.append(f"reference: {report['reference_from']}")
        return "\n".join(lines)
    w, x, y, z = ref["imu_to_marker"]
    lines += [f"clock offset {1e3 * ref['clock_offset_s']:+.1f} ms (IMU stamp − reference stamp), drift "
              f"{ref['clock_drift_ppm']:+.1f} ppm",
              f"IMU-to-marker rotation {ref['imu_to_marker_deg']:.2f}° (q = [{w:.4f}, {x:.4f}, {y:.4f}, {z:.4f}])",
              f"reference frame: tilt {ref['reference_tilt_deg']:.2f}°, heading {ref['reference_heading_deg']:+.2f}° "
              "(from the magnetometer)"]
    mag = ref["magnetometer"]
    if "gain" in mag:
        lines.append(f"magnetometer calibration {'applied' if mag['calibrated'] else 'FAILED, not applied'}: gain "
                     f"{np.round(mag['gain'], 3).tolist()}, bias {np.round(mag['bias_ut'], 2).tolist()} µT")
    res = ref["residuals_rms"]
    lines.append(f"residuals (RMS over {ref['reference_share']:.0%} of samples with a reference): gyro "
                 f"{res['gyr_dps']:.2f} °/s, acc {res['acc']:.3f} m/s², magnetometer heading spread "
                 f"{res['heading_deg']:.2f}°; qmt's costs (10 Hz low-pass): gyro {ref['qmt_gyr_cost']:.4f} rad/s, "
                 f"acc {ref['qmt_acc_cost']:.3f} m/s²")
    lines += [f"qmt: {w}" for w in ref["warnings"]]
    return "\n".join(lines)


def plot_residuals(time, res: dict, path) -> Path | None:
    """The residuals (``residuals``) over time as a PNG at ``path``; ``None`` (no plot) without
    matplotlib (the ``plot`` extra)."""
    try:
        require("matplotlib", extra="plot", what="the import's residual plot").use("Agg")
        plt = require("matplotlib.pyplot", extra="plot", what="the import's residual plot")
    except MissingExtraError:
        return None
    t = time - time[0]
    fig, axes = plt.subplots(3, 1, sharex=True, figsize=(9, 6.5))
    for ax, (key, label) in zip(axes, (("gyr_dps", "gyro − reference rate [°/s]"),
                                       ("acc", "|acc − gravity| in ENU [m/s²]"),
                                       ("heading_deg", "magnetometer heading [°]"))):
        ax.plot(t, res[key], lw=0.6)
        ax.set_ylabel(label, fontsize=8)
        ax.grid(alpha=0.3)
    axes[-1].set_xlabel("time [s]")
    fig.suptitle(f"{Path(path).name}: residuals of the aligned reference")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return Path(path)


# --------------------------------------------------------------------------------------- import

def _reference_for(imu: ImuLog, reference, settings: ImportSettings):
    """``(opt_quat (N, 4), opt_pos or None, mag (N, 3), report)`` from a reference log (aligned),
    the log's own quaternion columns (as they are), or nothing (NaN: filtered, not scored)."""
    if reference is None:
        how = ("the log's own quaternion columns, taken as synchronised and aligned" if imu.quat is not None
               else "none (opt_quat is NaN: the trial can be filtered, not scored)")
        q = imu.quat if imu.quat is not None else np.full((imu.time.size, 4), np.nan)
        return q, imu.pos, imu.mag, {"reference_from": how}
    if imu.quat is not None:
        raise DataError(imu.source, "q0", "the log has reference quaternions and --reference gives another "
                                          "reference: use one of them")
    ref = read_reference_log(reference, settings)
    opt_quat, opt_pos, mag, aligned = align_reference(imu, ref, settings)
    res = residuals(imu.time, imu.gyr, imu.acc, mag, opt_quat, aligned)
    aligned["residuals_rms"] = {k: _rms(v) for k, v in res.items()}
    aligned["reference_share"] = float(np.isfinite(opt_quat[:, 0]).mean())
    return opt_quat, opt_pos, mag, {"reference_from": str(ref.source), "reference": aligned, "residuals": res}


def import_recording(imu_path, out_dir, reference=None, *, name: str | None = None, groups=("imported",),
                     settings: ImportSettings = ImportSettings(), plot: bool = True) -> ImportResult:
    """Import one recording into the BROAD-layout directory ``out_dir`` (module docstring).

    Args:
        imu_path: the IMU log (``.csv``, ``.npz``, ``.npy``).
        out_dir: the data directory (created if needed); gets ``<name>.hdf5``, its line in
            ``trials.json``, ``<name>.import.json`` (the report) and, with a reference and
            matplotlib, ``<name>.import.png`` (the residuals over time).
        reference: a mocap log to synchronise and align (needs the ``import`` extra), or ``None``.
        name: the trial's name (default: the log's file stem); ``groups``: its groups in ``trials.json``.
        plot: draw the residual plot when there is a reference and matplotlib.

    Raises ``DataError`` (a ``ValueError``; one line naming file, column and problem) for bad input and
    ``MissingExtraError`` (naming the extra) for a reference without qmt, before anything is read.
    """
    if reference is not None:
        check_extra("import", what=REFERENCE_WHAT)
    imu = read_imu_log(imu_path, settings)
    name = name or imu.source.stem
    if not name or "/" in name or name.startswith("."):
        raise ValueError(f"--name: {name!r} cannot be a trial file's name")
    opt_quat, opt_pos, mag, ref = _reference_for(imu, reference, settings)
    fs = imu.fs
    if imu.movement is not None:
        movement, movement_from = imu.movement, "the log's movement column"
    else:
        movement = broad_movement(imu.gyr, fs, settings.rest_threshold, settings.min_rest_s, settings.rest_margin_s)
        movement_from = f"BROAD's rule: rests over {settings.min_rest_s:g} s not scored"
    try:
        trial = Trial(name, fs, imu.gyr, imu.acc, mag, opt_quat, opt_pos, movement, tuple(groups), imu.source,
                      time=imu.time)
    except DataError as exc:
        raise (_units_hint(exc, settings) if exc.field in ("gyr", "acc") else exc) from None
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    report = {"name": name, "source": str(imu.source), "n_samples": trial.n_samples,
              "duration_s": float(np.ptp(imu.time)), "sampling_rate": fs, "movement_share": float(movement.mean()),
              "movement_from": movement_from, "settings": dataclasses.asdict(settings),
              **{k: v for k, v in ref.items() if k != "residuals"}}
    report_file = atomic_write_json(out_dir / f"{name}.import.json", report)
    png = None
    if plot and "residuals" in ref:
        png = plot_residuals(imu.time, ref["residuals"], out_dir / f"{name}.import.png")
    info = f"togglecf import of {imu.source.name}\n" + summary_text(report)
    path = _write_trial(out_dir / f"{name}.hdf5", trial, info)
    description = f"imported from {imu.source.name}" + (f", reference {Path(reference).name}" if reference else "")
    index_file = add_to_index(out_dir, name, description, groups)  # last: the index lists only a written trial
    return ImportResult(trial, path, report, png, [path, report_file, *([png] if png else []), index_file])
