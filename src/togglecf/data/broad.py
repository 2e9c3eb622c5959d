"""BROAD data layer: one typed ``Trial``, loaders for both BROAD formats, the dataset index.

BROAD (Laidig et al., Data 6(7):72, 2021) ships each trial as HDF5 and as MATLAB v5 with
the fields ``imu_gyr`` [rad/s], ``imu_acc`` [m/s²], ``imu_mag`` [µT], ``opt_quat``
(sensor -> ENU, NaN rows where markers were lost), ``opt_pos`` [m], ``movement`` (bool)
and ``sampling_rate`` [Hz]; ``trials.json`` lists the 39 trials and 16 groups.

Any directory in this layout works (``trials.json`` + one file per trial). Evaluation needs only
``imu_gyr``, ``imu_acc``, ``imu_mag``, ``opt_quat``, ``movement`` and ``sampling_rate``;
``opt_pos`` is optional (``Trial.opt_pos`` is ``None`` without it): training's labels use it when
present (``togglecf.learn.labels``). ``imu_time`` (optional, not in BROAD) holds each sample's time stamp [s]
for a recording with an uneven clock (``togglecf import``); ``Trial.time`` is ``None`` without it.

Several directories at once: ``open_index([A, B])`` (or ``DatasetIndex.from_dirs``) gives a
``MultiIndex`` with the same interface, whose trial names carry their dataset
(``<dir name>/<trial>``, e.g. ``tyrex_nexus5/Guillaume_Nexus5_NoDist_AR``) and whose groups are
each directory's ``trials.json`` groups prefixed the same way, plus one group per dataset
(``tyrex_nexus5``: all its listed trials). With one directory nothing is prefixed.
"""
from __future__ import annotations

import fnmatch
import json
import os
import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from togglecf.core.units import UNIT_TABLES, unit_mismatch


__all__ = [
    "DataError", "DataNotFoundError", "Trial", "load_trial", "DatasetIndex",
    "resolve_data_dir", "BROAD_URL", "GRAVITY", "MAX_INVALID_FRACTION", "MIN_DURATION_S", "min_samples",
    "check_evaluable", "MultiIndex", "open_index", "resolve_data_dirs", "trial_fields", "REQUIRED_FIELDS",
    "OPTIONAL_FIELDS", "short_trial_name", "copy_hdf5_trial", "write_broad_hdf5", "checked_time_stamps",
]

GRAVITY = 9.81  # m/s², BROAD's accelerometers read ~9.81 at rest
BROAD_URL = "https://github.com/dlaidig/broad"
TRIAL_SUFFIXES = (".hdf5", ".mat")
_IMU_FIELDS = ("imu_gyr", "imu_acc", "imu_mag")

#: Largest fraction of a trial's samples that may be non-finite (NaN/inf) in one IMU field (gyr, acc
#: or mag) before the trial is refused. Below it, bad samples are kept and counted (``Trial.invalid``):
#: every filter skips the affected step (``filters/base.py``) and the metric scores the others. 10 %:
#: a recording with dropouts here and there stays usable; one that is mostly holes is reported, not
#: scored as if it were a measurement of the filter.
MAX_INVALID_FRACTION = 0.10

#: Shortest recording that is loaded and evaluated [s]. BROAD's errors are RMSEs over the movement
#: samples after the filters have started; the toggling filter makes its first prediction after one
#: feature window (0.2 s) and every filter starts from the first sample, so a recording of under a
#: second is scored on start-up transients (or, with no movement sample, on nothing: a table of
#: NaN). BROAD's trials are 2-5 minutes long; its shortest movement phases last tens of seconds.
MIN_DURATION_S = 1.0


def min_samples(fs: float) -> int:
    """The fewest samples a recording at ``fs`` [Hz] may have: ``MIN_DURATION_S`` rounded down."""
    return max(2, int(np.floor(MIN_DURATION_S * fs + 1e-9)))


class DataError(ValueError):
    """Bad input data. The message names the file, the field and the problem."""

    def __init__(self, source, field_name: str | None, problem: str):
        where = str(source) if source is not None else "<in memory>"
        if field_name:
            where += f": field '{field_name}'"
        super().__init__(f"{where}: {problem}")
        self.source, self.field, self.problem = source, field_name, problem


class DataNotFoundError(FileNotFoundError):
    """No BROAD data where it was looked for."""


@dataclass(frozen=True, eq=False)
class Trial:
    """One recording: IMU signals plus (optionally) optical ground truth.

    Attributes (N samples):
        name: trial name, e.g. ``02_undisturbed_slow_rotation_B``.
        fs: sampling rate [Hz].
        gyr, acc, mag: ``(N, 3)`` float64 in rad/s, m/s², µT (sensor frame).
        opt_quat: ``(N, 4)`` sensor -> ENU ground truth; NaN rows where unavailable.
        opt_pos: ``(N, 3)`` [m] marker position, NaN rows where unavailable; ``None`` when the
            recording has none (evaluation does not need it; training's labels do).
        movement: ``(N,)`` bool, the samples errors are scored on.
        groups: BROAD group names of this trial.
        source: file it was read from, if any.
        time: ``(N,)`` time stamp of each sample [s], strictly increasing, for a recording whose
            samples are not evenly spaced (``imu_time``, written by ``togglecf import``); ``None``
            when the samples are ``1/fs`` apart (BROAD). ``fs`` is then the nominal (median) rate.
    """

    name: str
    fs: float
    gyr: np.ndarray
    acc: np.ndarray
    mag: np.ndarray
    opt_quat: np.ndarray
    opt_pos: np.ndarray | None
    movement: np.ndarray
    groups: tuple[str, ...] = ()
    source: Path | None = None
    check_units: bool = field(default=True, repr=False)
    time: np.ndarray | None = field(default=None, repr=False)
    #: non-finite (NaN/inf) samples per IMU field: ``{"gyr": k, "acc": k, "mag": k}`` (set on construction)
    invalid: dict = field(init=False, repr=False, compare=False)

    def __post_init__(self):
        src = self.source if self.source is not None else self.name
        if not (np.isscalar(self.fs) and np.isfinite(self.fs) and self.fs > 0):
            raise DataError(src, "sampling_rate", f"must be a positive finite number in Hz, got {self.fs!r}")
        object.__setattr__(self, "fs", float(self.fs))
        n = None
        for name, width in (("gyr", 3), ("acc", 3), ("mag", 3), ("opt_quat", 4), ("opt_pos", 3)):
            if name == "opt_pos" and self.opt_pos is None:
                continue
            arr = np.ascontiguousarray(getattr(self, name), dtype=np.float64)
            if arr.ndim != 2 or arr.shape[1] != width:
                raise DataError(src, name, f"expected shape (N, {width}), got {arr.shape}")
            n = arr.shape[0] if n is None else n
            if arr.shape[0] != n:
                raise DataError(src, name, f"has {arr.shape[0]} samples, gyr has {n}")
            object.__setattr__(self, name, arr)
        if n == 0:
            raise DataError(src, "gyr", "trial has no samples")
        mov = np.asarray(self.movement)
        if mov.ndim == 2 and 1 in mov.shape:
            mov = mov.reshape(-1)
        if mov.shape != (n,):
            raise DataError(src, "movement", f"expected shape ({n},), got {mov.shape}")
        if mov.dtype != bool:
            if not np.all(np.isin(mov, (0, 1))):
                raise DataError(src, "movement", "must be boolean (0/1)")
            mov = mov.astype(bool)
        object.__setattr__(self, "movement", mov)
        object.__setattr__(self, "groups", tuple(self.groups))
        if self.time is not None:
            object.__setattr__(self, "time", _checked_time(src, self.time, n))
        invalid = {}
        for name in ("gyr", "acc", "mag"):
            bad = ~np.all(np.isfinite(getattr(self, name)), axis=1)
            invalid[name] = int(bad.sum())
            if invalid[name] > MAX_INVALID_FRACTION * n:
                raise DataError(src, name, f"{invalid[name]} of {n} samples ({invalid[name] / n:.1%}) are not finite "
                                f"(NaN/inf; first at index {np.argmax(bad)}); at most "
                                f"{MAX_INVALID_FRACTION:.0%} may be (togglecf.data.broad.MAX_INVALID_FRACTION)")
        object.__setattr__(self, "invalid", invalid)
        for name in ("opt_quat", "opt_pos"):
            arr = getattr(self, name)
            if arr is None:
                continue
            fin = np.isfinite(arr)
            if np.any(fin.any(axis=1) & ~fin.all(axis=1)):
                raise DataError(src, name, "rows must be all finite or all NaN")
        q = self.opt_quat[np.isfinite(self.opt_quat[:, 0])]
        if q.size and np.max(np.abs(np.linalg.norm(q, axis=1) - 1.0)) > 1e-3:
            raise DataError(src, "opt_quat", "ground-truth quaternions are not unit norm")
        if self.check_units:
            self._check_units(src)

    def _check_units(self, src):
        """Units another unit explains (``core.units.unit_mismatch``: g, mg, °/s, gauss, mT, nT), and an
        accelerometer without gravity: ``DataError`` naming the field."""
        for quantity, samples in (("acc", self.acc), ("gyr", self.gyr), ("mag", self.mag)):
            if not np.isfinite(samples).all(axis=1).any():
                if quantity != "mag":
                    raise DataError(src, quantity, "no finite sample")
                continue
            wrong = unit_mismatch(quantity, samples)
            if wrong is not None:
                raise DataError(src, quantity, f"{wrong.describe()} (multiply by "
                                               f"{UNIT_TABLES[quantity][wrong.unit]:.6g})")
        acc_norm = float(np.nanmedian(np.linalg.norm(self.acc, axis=1)))
        if acc_norm <= 0.5:
            raise DataError(src, "acc", f"median |acc| = {acc_norm:.3g} m/s²: no gravity in the signal (expected "
                                        f"~{GRAVITY}); a unit or scale error")

    @property
    def n_samples(self) -> int:
        return self.gyr.shape[0]

    @property
    def duration(self) -> float:
        """Length in seconds."""
        return self.n_samples / self.fs

    @property
    def n_invalid(self) -> int:
        """Samples with a non-finite value in any IMU field (the filters skip their update)."""
        ok = np.isfinite(self.gyr).all(axis=1) & np.isfinite(self.acc).all(axis=1) & np.isfinite(self.mag).all(axis=1)
        bad = ~ok
        return int(bad.sum())

    def slice(self, start: int, stop: int) -> "Trial":
        """A sub-trial of samples ``start:stop`` (same name with a suffix)."""
        sl = np.s_[start:stop]
        return Trial(f"{self.name}[{start}:{stop}]", self.fs, self.gyr[sl], self.acc[sl], self.mag[sl],
                     self.opt_quat[sl], None if self.opt_pos is None else self.opt_pos[sl], self.movement[sl],
                     self.groups, self.source, check_units=False, time=None if self.time is None else self.time[sl])


def _checked_time(src, time, n: int) -> np.ndarray:
    """``time`` as float64 ``(n,)``, finite and strictly increasing; else ``DataError`` on ``imu_time``."""
    t = np.asarray(time, dtype=np.float64)
    if t.ndim == 2 and 1 in t.shape:  # MATLAB's column vector
        t = t.reshape(-1)
    if t.shape != (n,):
        raise DataError(src, "imu_time", f"expected shape ({n},), got {t.shape}")
    return checked_time_stamps(src, "imu_time", t)


def checked_time_stamps(src, field_name: str, t, unit: str = "s", to_seconds: float = 1.0) -> np.ndarray:
    """Time stamps ``t (N,)`` in ``unit`` as float64 seconds (times ``to_seconds``); ``DataError`` on
    ``field_name`` of ``src`` naming the first row that is not finite or does not increase."""
    t = np.asarray(t, dtype=np.float64)
    if not np.all(np.isfinite(t)):
        raise DataError(src, field_name, f"row {int(np.argmin(np.isfinite(t)))} has no time stamp (not finite)")
    steps = np.diff(t)
    if np.any(steps <= 0):
        k = int(np.argmax(steps <= 0)) + 1
        raise DataError(src, field_name, f"time stamps must increase: row {k} ({t[k]:.10g} {unit}) follows "
                                         f"{t[k - 1]:.10g} {unit}")
    return t * to_seconds


# ------------------------------------------------------------------------------------------ loading

def short_trial_name(name: str) -> str:
    """A trial's name for logs and narrow tables: BROAD's numbered names by their number
    (``02_undisturbed_slow_rotation_B`` -> ``02``), other names whole, a dataset prefix kept
    (``broad/02``, ``tyrex_nexus5/Thibaud_Nexus5_NoDist_Texting``)."""
    prefix, sep, local = name.rpartition("/")
    head = local.split("_")[0]
    return prefix + sep + (head if head.isdigit() else local)


def load_trial(path, groups=(), check_units: bool = True, name: str | None = None) -> Trial:
    """Read one BROAD trial from ``.hdf5`` or ``.mat`` (``name``: default the file's stem).

    ``REQUIRED_FIELDS`` must be there; ``opt_pos`` may be absent (``Trial.opt_pos`` is ``None``).

    Raises ``DataError`` naming the file and field for a missing dataset, wrong shape, a recording
    shorter than ``MIN_DURATION_S``, more than ``MAX_INVALID_FRACTION`` non-finite samples in an IMU
    field, implausible units or an unreadable (corrupt/truncated) file. Fewer non-finite samples are
    kept and counted in ``Trial.invalid``.
    """
    path = Path(path)
    if not path.is_file():
        raise DataError(path, None, "file not found")
    suffix = path.suffix.lower()
    if suffix == ".hdf5" or suffix == ".h5":
        fields, fs = _read_hdf5(path)
    elif suffix == ".mat":
        fields, fs = _read_mat(path)
    else:
        raise DataError(path, None, f"unknown trial format {suffix!r}; expected .hdf5 or .mat")
    n = int(np.shape(fields["imu_gyr"])[0]) if np.ndim(fields["imu_gyr"]) else 0
    if 0 < fs and n < min_samples(fs):
        raise DataError(path, "imu_gyr", f"{n} samples ({n / fs:.2f} s at {fs:.1f} Hz) is too short: at least "
                        f"{min_samples(fs)} samples ({MIN_DURATION_S:g} s, togglecf.data.broad.MIN_DURATION_S) are "
                        "needed to evaluate a filter")
    return Trial(name=name or path.stem, fs=fs, gyr=fields["imu_gyr"], acc=fields["imu_acc"], mag=fields["imu_mag"],
                 opt_quat=fields["opt_quat"], opt_pos=fields.get("opt_pos"), movement=fields["movement"],
                 groups=tuple(groups), source=path, check_units=check_units, time=fields.get("imu_time"))


def check_evaluable(trial: Trial) -> Trial:
    """Refuse (``DataError`` naming the file) a trial whose BROAD errors cannot be computed: shorter
    than ``MIN_DURATION_S``, or without a sample that is both movement and has ground truth (the
    RMSEs would be NaN). Returns the trial."""
    src = trial.source if trial.source is not None else trial.name
    n_min = min_samples(trial.fs)
    if trial.n_samples < n_min:
        raise DataError(src, "gyr", f"{trial.n_samples} samples ({trial.duration:.2f} s at {trial.fs:.1f} Hz) is too "
                        f"short: at least {n_min} samples ({MIN_DURATION_S:g} s, togglecf.data.broad.MIN_DURATION_S) "
                        "are needed to evaluate a filter")
    if not np.any(trial.movement & np.isfinite(trial.opt_quat).all(axis=1)):
        raise DataError(src, "movement", "no sample is both marked as movement and has ground truth (opt_quat): "
                        "BROAD's errors (RMSE over those samples) cannot be computed")
    return trial


#: what every trial file must hold (besides ``sampling_rate``): all that evaluation needs
REQUIRED_FIELDS = ("imu_gyr", "imu_acc", "imu_mag", "opt_quat", "movement")
#: read when present: ``opt_pos`` (training's labels use it, ``togglecf.learn.labels``) and ``imu_time``
#: (each sample's time stamp [s], ``Trial.time``)
OPTIONAL_FIELDS = ("opt_pos", "imu_time")
_REQUIRED = REQUIRED_FIELDS


def trial_fields(path) -> set[str]:
    """The dataset/variable names a trial file holds, without reading the arrays."""
    path = Path(path)
    h5py = None if path.suffix.lower() == ".mat" else _h5py()
    try:
        if h5py is None:
            import scipy.io

            return {n for n, *_ in scipy.io.whosmat(path)}
        with h5py.File(path, "r") as f:
            return set(f.keys())
    except Exception as exc:  # corrupt files: the loader says what is wrong
        raise DataError(path, None, f"cannot read trial file (corrupt or truncated?): {exc}") from None


def _h5py():
    """h5py (a dependency), imported on first use: the command line's --help stays light."""
    import h5py

    return h5py


def copy_hdf5_trial(src, dest, drop=()) -> Path:
    """The HDF5 trial file ``src`` copied to ``dest`` with its attributes, without the datasets ``drop``
    (e.g. ``("opt_pos",)``: a recording without an optical position)."""
    h5py = _h5py()
    dest = Path(dest)
    with h5py.File(src, "r") as fi, h5py.File(dest, "w") as fo:
        for k in fi:
            if k not in drop:
                fo.create_dataset(k, data=fi[k][()])
        for k, v in fi.attrs.items():
            fo.attrs[k] = v
    return dest


def write_broad_hdf5(path, trial: Trial, info: str) -> None:
    """Write ``trial`` as one HDF5 file in BROAD's layout: the datasets ``imu_gyr``, ``imu_acc``,
    ``imu_mag``, ``opt_quat``, ``opt_pos`` (float64; left out when ``trial.opt_pos`` is ``None``),
    ``movement`` (bool) and, when ``trial.time`` is set, ``imu_time`` [s], gzip-compressed, and the file
    attributes ``sampling_rate`` [Hz] and ``info`` (say where the data come from). No HDF5 timestamps:
    the same trial gives the same bytes."""
    h5py = _h5py()
    fields = {"imu_gyr": trial.gyr, "imu_acc": trial.acc, "imu_mag": trial.mag, "opt_quat": trial.opt_quat,
              "opt_pos": trial.opt_pos, "movement": np.asarray(trial.movement, bool), "imu_time": trial.time}
    with h5py.File(path, "w", track_order=True) as f:
        f.attrs["sampling_rate"] = float(trial.fs)
        f.attrs["info"] = info
        for k, v in fields.items():
            if v is not None:
                f.create_dataset(k, data=v, dtype=bool if k == "movement" else np.float64, compression="gzip",
                                 compression_opts=9, track_times=False)


def _read_hdf5(path: Path):
    h5py = _h5py()
    try:
        with h5py.File(path, "r") as f:
            missing = [k for k in _REQUIRED if k not in f]
            if missing:
                raise DataError(path, missing[0], f"missing dataset (file has: {sorted(f.keys())})")
            if "sampling_rate" in f.attrs:
                fs = f.attrs["sampling_rate"]
            elif "sampling_rate" in f:
                fs = f["sampling_rate"][()]
            else:
                raise DataError(path, "sampling_rate", "missing file attribute")
            fields = {k: f[k][()] for k in _REQUIRED + OPTIONAL_FIELDS if k in f}
    except DataError:
        raise
    except OSError as exc:  # h5py raises OSError for corrupt or truncated files
        raise DataError(path, None, f"cannot read HDF5 file (corrupt or truncated?): {exc}") from None
    return fields, _scalar(path, fs)


def _read_mat(path: Path):
    import scipy.io

    try:
        mat = scipy.io.loadmat(path)
    except Exception as exc:  # scipy raises ValueError/TypeError/OSError for damaged files
        raise DataError(path, None, f"cannot read MAT file (corrupt or truncated?): {exc}") from None
    missing = [k for k in _REQUIRED + ("sampling_rate",) if k not in mat]
    if missing:
        have = sorted(k for k in mat if not k.startswith("__"))
        raise DataError(path, missing[0], f"missing variable (file has: {have})")
    return {k: mat[k] for k in _REQUIRED + OPTIONAL_FIELDS if k in mat}, _scalar(path, mat["sampling_rate"])


def _scalar(path, value) -> float:
    arr = np.asarray(value, dtype=np.float64)
    if arr.size != 1:
        raise DataError(path, "sampling_rate", f"expected a scalar, got shape {arr.shape}")
    return float(arr.reshape(()))


# ------------------------------------------------------------------------------------ dataset index

@dataclass
class DatasetIndex:
    """What a BROAD directory holds, checked against its ``trials.json``.

    Attributes:
        root: the directory.
        trials: listed trial name -> info dict (``description``, ``groups``) for all listed trials.
        groups: group name -> list of listed trial names, in ``trials.json`` order.
        available: listed trial name -> file path, for the trials present (HDF5 preferred).
        missing: listed trials with no file.
        unlisted: trial files in the directory that ``trials.json`` does not list (not used).
    """

    root: Path
    trials: dict
    groups: dict
    available: dict
    missing: list
    unlisted: list

    @classmethod
    def from_dir(cls, root) -> "DatasetIndex":
        root = Path(root)
        index_file = root / "trials.json"
        if not index_file.is_file():
            raise DataNotFoundError(f"{root}: no trials.json (BROAD's trial index); {_WHERE_TO_GET}")
        try:
            info = json.loads(index_file.read_text())
            trials = dict(info["trials"])
            group_names = [g["name"] for g in info["groups"]]
        except (ValueError, KeyError, TypeError) as exc:
            raise DataError(index_file, None, f"not a BROAD trials.json: {exc}") from None
        groups = {g: [t for t, ti in trials.items() if g in ti.get("groups", ())] for g in group_names}
        files = {}
        for p in sorted(root.iterdir()):
            if p.suffix.lower() in TRIAL_SUFFIXES and p.is_file():
                files.setdefault(p.stem, []).append(p)
        available, missing = {}, []
        for name in trials:
            cands = sorted(files.get(name, []), key=lambda p: TRIAL_SUFFIXES.index(p.suffix.lower()))
            if cands:
                available[name] = cands[0]
            else:
                missing.append(name)
        unlisted = [p for stem, ps in files.items() if stem not in trials for p in ps]
        return cls(root, trials, groups, available, missing, unlisted)

    @classmethod
    def from_dirs(cls, roots) -> "DatasetIndex | MultiIndex":
        """One directory: its ``DatasetIndex``; several: their ``MultiIndex`` (see ``open_index``)."""
        return open_index(list(roots))

    @property
    def roots(self) -> tuple[Path, ...]:
        return (Path(self.root),)

    def select(self, spec: str | list[str] | None = None) -> list[str]:
        """Available trial names matching ``spec`` (see ``select_trials``)."""
        return _select_one(self, spec, prefix=Path(self.root).name)

    def trial_groups(self, name: str) -> tuple[str, ...]:
        return tuple(self.trials[name].get("groups", ()))

    def load(self, name: str, check_units: bool = True) -> Trial:
        if name not in self.available:
            raise KeyError(f"trial {name} is not present in {self.root}")
        return load_trial(self.available[name], groups=self.trial_groups(name), check_units=check_units)

    def dataset_of(self, name: str) -> str:
        """The dataset a trial belongs to: the directory's name."""
        return Path(self.root).name

    def summary(self) -> str:
        lines = [f"BROAD at {self.root}: {len(self.available)} of {len(self.trials)} listed trials present"]
        if self.missing:
            lines.append(f"missing ({len(self.missing)}): " + ", ".join(self.missing))
        if self.unlisted:
            lines.append("not in trials.json, ignored: " + ", ".join(p.name for p in self.unlisted))
        return "\n".join(lines)


_GLOB_CHARS = set("*?[")

#: how ``--trials`` / ``[run] trials`` select (the same for one directory and for several)
SELECTION_HELP = (
    "comma-separated items; each a trial number (02), a full name or a name prefix, a glob (*NoDist*, "
    "tyrex_nexus5/*_AR), or with several --data directories DATASET/ITEM (broad/02) or DATASET/ for all of "
    "a dataset's trials (DATASET is the directory's name); 'all' or nothing selects every trial present"
)


def _match(trials, item: str) -> list[str]:
    """Listed trial names that ``item`` selects: a glob, or a number / full name / name prefix."""
    if _GLOB_CHARS & set(item):
        return [t for t in trials if fnmatch.fnmatchcase(t, item)]
    pattern = re.compile(rf"^{re.escape(item.zfill(2) if item.isdigit() else item)}(_|$)")
    return [t for t in trials if pattern.match(t) or t == item]


def _items(spec) -> list[str] | None:
    if spec is None or spec == "" or spec == "all":
        return None
    items = spec.split(",") if isinstance(spec, str) else list(spec)
    items = [s.strip() for s in items if s and s.strip()]
    return items or None


def _keep_available(index, item, hits, out, where):
    if not hits:
        raise KeyError(f"trial {item!r} is not listed in {where}")
    absent = [t for t in hits if t not in index.available]
    if absent and len(absent) == len(hits):
        raise KeyError(f"trial {absent[0]} is listed but not present in {index.root}")
    out.extend(t for t in hits if t in index.available and t not in out)


def _select_one(index: "DatasetIndex", spec, prefix: str | None = None) -> list[str]:
    """``DatasetIndex.select``: also accepts ``<directory name>/ITEM`` and ``<directory name>/``, so a
    selection written for several directories works on one of them."""
    items = _items(spec)
    if items is None:
        return list(index.available)
    out = []
    for item in items:
        if prefix and item.startswith(prefix + "/"):
            item = item[len(prefix) + 1:] or "*"
        _keep_available(index, item, _match(index.trials, item), out, Path(index.root) / "trials.json")
    return out


@dataclass
class MultiIndex:
    """Several BROAD-layout directories as one index (the interface of ``DatasetIndex``).

    Trial names are ``<dataset>/<trial>`` with ``<dataset>`` the directory's name; groups are
    ``<dataset>`` (all of its listed trials) and ``<dataset>/<group>`` for each group of its
    ``trials.json``. ``root`` is the tuple of directories (what ``open_index`` takes back, e.g.
    on a worker).
    """

    datasets: dict  # dataset name -> DatasetIndex, in the order given
    trials: dict = field(init=False)
    groups: dict = field(init=False)
    available: dict = field(init=False)
    missing: list = field(init=False)
    unlisted: list = field(init=False)

    def __post_init__(self):
        self.trials, self.groups, self.available, self.missing, self.unlisted = {}, {}, {}, [], []
        for ds, idx in self.datasets.items():
            self.groups[ds] = [f"{ds}/{t}" for t in idx.trials]
            for t, info in idx.trials.items():
                self.trials[f"{ds}/{t}"] = {**info, "groups": [ds] + [f"{ds}/{g}" for g in info.get("groups", ())]}
            for g, members in idx.groups.items():
                self.groups[f"{ds}/{g}"] = [f"{ds}/{t}" for t in members]
            self.available.update({f"{ds}/{t}": p for t, p in idx.available.items()})
            self.missing.extend(f"{ds}/{t}" for t in idx.missing)
            self.unlisted.extend(idx.unlisted)

    @classmethod
    def from_dirs(cls, roots) -> "MultiIndex":
        datasets = {}
        for root in roots:
            root = Path(root)
            idx = DatasetIndex.from_dir(root)
            ds = root.resolve().name
            if ds in datasets:
                raise ValueError(f"two data directories are both called {ds!r} ({datasets[ds].root} and {root}): trial "
                                 "names carry the directory's name, so give one of them another name (or a symlink)")
            datasets[ds] = idx
        if not datasets:
            raise DataNotFoundError(f"no data directory given; {_WHERE_TO_GET}")
        return cls(datasets)

    @property
    def root(self) -> tuple[Path, ...]:
        return tuple(Path(idx.root) for idx in self.datasets.values())

    roots = root

    def split(self, name: str) -> tuple[str, str]:
        """``"broad/02_..."`` -> ``("broad", "02_...")``; ``KeyError`` for an unknown dataset."""
        ds, sep, local = name.partition("/")
        if not sep or ds not in self.datasets:
            raise KeyError(f"trial {name!r}: names are <dataset>/<trial> with <dataset> one of {list(self.datasets)}")
        return ds, local

    def dataset_of(self, name: str) -> str:
        return self.split(name)[0]

    def select(self, spec: str | list[str] | None = None) -> list[str]:
        """Available trial names matching ``spec`` (``SELECTION_HELP``): ``DATASET/`` all of a dataset,
        ``DATASET/ITEM`` an item within it, a glob over the full names, or an item without a dataset,
        matched in every dataset. Unknown or unavailable ones raise ``KeyError``."""
        items = _items(spec)
        if items is None:
            return list(self.available)
        out = []
        for item in items:
            ds, sep, rest = item.partition("/")
            if sep and ds in self.datasets and not (_GLOB_CHARS & set(ds)):
                idx = self.datasets[ds]
                hits = [f"{ds}/{t}" for t in _match(idx.trials, rest or "*")]
                where = Path(idx.root) / "trials.json"
            elif _GLOB_CHARS & set(item):
                hits, where = _match(self.trials, item), "any of " + ", ".join(str(r) for r in self.root)
            else:
                hits = [f"{d}/{t}" for d, idx in self.datasets.items() for t in _match(idx.trials, item)]
                where = "the trials.json of " + ", ".join(str(r) for r in self.root)
            _keep_available(self, item, hits, out, where)
        return out

    def trial_groups(self, name: str) -> tuple[str, ...]:
        return tuple(self.trials[name].get("groups", ()))

    def load(self, name: str, check_units: bool = True) -> Trial:
        if name not in self.available:
            raise KeyError(f"trial {name} is not present in {', '.join(str(r) for r in self.root)}")
        return load_trial(self.available[name], groups=self.trial_groups(name), check_units=check_units, name=name)

    def summary(self) -> str:
        lines = [f"{len(self.datasets)} datasets: {len(self.available)} of {len(self.trials)} listed trials present"]
        for ds, idx in self.datasets.items():
            lines.append(f"  {ds}/: " + idx.summary().replace("BROAD at ", "").replace("\n", "\n    "))
        return "\n".join(lines)


def open_index(data=None) -> "DatasetIndex | MultiIndex":
    """The index of one data directory or of several: ``data`` is ``None`` (the default location,
    ``resolve_data_dir``), a directory, or a list/tuple of directories (each must hold a
    ``trials.json``). One directory (also a list of one) gives a ``DatasetIndex`` with the trial names
    as they are; several give a ``MultiIndex`` (names ``<dataset>/<trial>``)."""
    dirs = resolve_data_dirs(data)
    if len(dirs) == 1:
        return DatasetIndex.from_dir(dirs[0])
    return MultiIndex.from_dirs(dirs)


# ---------------------------------------------------------------------------- data-dir resolution

ENV_DATA = "TOGGLECF_DATA"
_WHERE_TO_GET = (
    "put BROAD's trial files (.hdf5 or .mat) and trials.json in one directory and pass it with "
    f"--data DIR or the environment variable {ENV_DATA}, or run `togglecf download ./data/broad` "
    f"to fetch them from {BROAD_URL}"
)


def repo_root() -> Path | None:
    """The source checkout this package runs from (editable install), if any."""
    here = Path(__file__).resolve()
    for parent in here.parents:
        if (parent / "pyproject.toml").is_file() and (parent / "src" / "togglecf").is_dir():
            return parent
    return None


def candidate_data_dirs(cli_dir=None) -> list[tuple[str, Path]]:
    """Where BROAD is looked for, in order: ``--data`` > ``$TOGGLECF_DATA`` >
    ``../shared/data/broad`` next to the repo > ``./data/broad``."""
    cands = []
    if cli_dir:
        cands.append(("--data", Path(cli_dir)))
    if os.environ.get(ENV_DATA):
        cands.append((f"${ENV_DATA}", Path(os.environ[ENV_DATA])))
    root = repo_root()
    if root is not None:
        cands.append(("next to the repo", root.parent / "shared" / "data" / "broad"))
    cands.append(("next to the working directory", Path.cwd().parent / "shared" / "data" / "broad"))
    cands.append(("default download location", Path.cwd() / "data" / "broad"))
    return cands


def resolve_data_dirs(data=None) -> list[Path]:
    """``resolve_data_dir`` of each directory of ``data`` (``None``, one directory or a list of them;
    an empty list is ``None``), the same directory given twice kept once."""
    if isinstance(data, (list, tuple)):
        data = [d for d in data if d not in (None, "")]
    if not data:
        return [resolve_data_dir(None)]
    out = []
    for d in ([data] if isinstance(data, (str, os.PathLike)) else data):
        p = resolve_data_dir(d)
        if p not in out:
            out.append(p)
    return out


def resolve_data_dir(cli_dir=None) -> Path:
    """The first candidate directory that holds ``trials.json``.

    An explicit ``--data`` or ``$TOGGLECF_DATA`` that does not hold data is an error, not
    a reason to silently fall through to another location.
    """
    tried = []
    for how, path in candidate_data_dirs(cli_dir):
        if (path / "trials.json").is_file():
            return path.resolve()
        tried.append(f"  {how}: {path}")
        if how in ("--data", f"${ENV_DATA}"):
            raise DataNotFoundError(f"no BROAD data in {path} (given by {how}): no trials.json there; {_WHERE_TO_GET}")
    raise DataNotFoundError("BROAD data not found. Looked in:\n" + "\n".join(tried) + f"\nTo fix: {_WHERE_TO_GET}.")
