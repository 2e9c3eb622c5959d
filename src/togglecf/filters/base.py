"""What every orientation filter in togglecf shares (modelled on VQF's design).

A filter is *settings* (a dataclass with documented defaults and units) + *state* (a flat
float64 vector that ``get_state``/``set_state`` save and restore exactly) + *coefficients*
derived from the settings and the sampling time ``Ts = 1/fs``.

The maths lives in one numba function per filter, ``step(state, params, gyr, acc, mag, dt,
diag)``, which advances ``state`` by one sample in place and writes diagnostics into
``diag``. ``update`` calls it for one sample and ``update_batch`` runs it over arrays in the
shared compiled loop ``run_batch``, so both give bit-identical results.

State layout: ``state[0:4]`` the orientation quaternion (sensor -> ENU, ``[w,x,y,z]``),
``state[4]`` 1.0 once initialised from the first valid acc(/mag) sample, ``state[5:]``
filter specific. A kernel may read the whole vector as a named record (fields by name in numba,
no offsets): ``state_record`` builds that numpy structured dtype and the flat ``state_names`` from
one list of fields, ``record_view`` the numba function that reads the flat vector as that record.

Coefficients: ``params`` is a named record, the filter class's ``Coefficients`` (a
``typing.NamedTuple``, which numba compiles to a struct: ``params.alpha`` costs the same as
indexing an array). Its first two fields are common to all filters: ``use_mag`` (1.0 for 9D,
the magnetometer is used; 0.0 for 6D) and ``max_dt`` (the largest Δt [s] that is still
integrated); the filter's own follow, named after what they are (``alpha``, ``beta``, ...,
mostly the names of its settings). ``_coefficients()`` returns those by name, and
``OrientationFilter.__init__`` builds ``params = Coefficients(use_mag=..., max_dt=...,
**self._coefficients())``, converting each value to the field's declared type (``float``,
``int`` or a contiguous float64 ``np.ndarray``) so that a filter compiles once per mode, not
once per combination of Python value types. Kernels read ``params.<name>``, never ``params[i]``.

Bad samples (documented policy, the same for all filters):

* non-finite gyro, a gyro axis at or beyond ``GYRO_FULL_SCALE`` (a saturated reading; judged
  on the raw reading, before any bias correction: ``gyro_valid``), or Δt that is non-finite,
  <= 0 or > ``max_dt`` (``dt_valid``): no gyro propagation, and no bias learning from that
  gyro sample. Madgwick and Mahony, whose correction is part of the same first-order step, then
  take the rate as zero (ω = 0, resp. ω − b̂ = 0) and still apply the correction; an invalid Δt
  skips their sample entirely;
* non-finite or zero-norm accelerometer: no correction at all for that sample;
* non-finite or zero-norm magnetometer (9D): no heading correction for that sample.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, fields, replace
from typing import ClassVar, NamedTuple, get_type_hints

import numba
import numpy as np
from numba import njit, types
from numba.extending import intrinsic

from togglecf.core.quaternion import (
    from_acc_mag_scalar,
    from_rotvec_scalar,
    multiply_scalar,
    normalize_scalar,
    rotate_scalar,
    to_frame,
)

__all__ = [
    "COMMON_STATE_FIELDS",
    "COMMON_COEFFICIENTS",
    "CommonCoefficients",
    "FilterOutput",
    "FilterSettings",
    "OrientationFilter",
    "dt_from_timestamps",
    "make_coefficients",
    "record_fields",
    "record_of",
    "record_view",
    "run_batch",
    "state_record",
]

N_COMMON_STATE = 5
#: the first fields of every filter's ``Coefficients``, in this order
COMMON_COEFFICIENTS = ("use_mag", "max_dt")
#: rad/s: ±2000 °/s, the largest full scale of common MEMS gyros. A reading at or beyond it is
#: saturated (the true rate is unknown), so it is not integrated. BROAD's largest is 25.2 rad/s.
GYRO_FULL_SCALE = 34.9


@dataclass(frozen=True)
class FilterSettings:
    """Settings shared by all filters.

    Attributes:
        max_dt: largest time step [s] that is still integrated; a longer gap (lost samples)
            skips gyro propagation for that sample. Default 0.1 s.
    """

    max_dt: float = 0.1

    def __post_init__(self):
        for f in fields(self):
            v = getattr(self, f.name)
            if isinstance(v, (int, float)) and not isinstance(v, bool) and not math.isfinite(v):
                raise ValueError(f"{type(self).__name__}.{f.name} must be finite, got {v}")
        if not self.max_dt > 0:
            raise ValueError(f"max_dt must be > 0 s, got {self.max_dt}")


class CommonCoefficients(NamedTuple):
    """The coefficients every filter has; each filter's ``Coefficients`` starts with these two
    fields (a ``NamedTuple`` cannot inherit fields, so they are repeated there).

    Attributes:
        use_mag: 1.0 for 9D (the magnetometer is used), 0.0 for 6D.
        max_dt: largest Δt [s] that is still integrated (``FilterSettings.max_dt``).
    """

    use_mag: float
    max_dt: float


def _is_record(kind) -> bool:
    return isinstance(kind, type) and issubclass(kind, tuple) and hasattr(kind, "_fields")


def make_coefficients(record: type, **values):
    """``record(**values)`` with each value converted to the field's declared type: ``float``,
    ``int``, ``np.ndarray`` (-> contiguous float64) or a nested ``NamedTuple`` (given as one, or
    as a dict; converted likewise). Missing or unknown names raise."""
    hints = get_type_hints(record)
    missing = [f for f in record._fields if f not in values]
    unknown = sorted(set(values) - set(record._fields))
    if missing or unknown:
        raise TypeError(f"{record.__qualname__}: missing coefficient(s) {missing}, unknown {unknown}")
    out = {}
    for f in record._fields:
        kind, v = hints[f], values[f]
        if kind is float:
            out[f] = float(v)
        elif kind is int:
            if int(v) != v:
                raise ValueError(f"{record.__qualname__}.{f} must be an integer, got {v!r}")
            out[f] = int(v)
        elif kind is np.ndarray:
            out[f] = np.ascontiguousarray(v, dtype=np.float64)
        elif _is_record(kind):
            out[f] = make_coefficients(kind, **(v._asdict() if isinstance(v, tuple) else v))
        else:
            raise TypeError(f"{record.__qualname__}.{f}: unsupported field type {kind!r}")
    return record(**out)


#: the common part of every state record (``state[0:5]``): (field, names) pairs, the first fields of every
#: filter's state and of its C twin's struct (``tests/test_names.py`` compares them)
COMMON_STATE_FIELDS = (("quat", ("quat_w", "quat_x", "quat_y", "quat_z")), ("initialized", "initialized"))


def _record_layout(fields) -> tuple[list, list]:
    dtype, names = [], []
    for name, spec in fields:
        if isinstance(spec, str):  # one float
            dtype.append((name, np.float64))
            names.append(spec)
        elif isinstance(spec, tuple):  # a vector (tuple of names) or matrix (tuple of tuples) of floats
            shape = np.shape(spec)
            dtype.append((name, np.float64, shape))
            names.extend(np.ravel(spec).tolist())
        else:  # a nested record: a list of fields
            sub, sub_names = _record_layout(spec)
            dtype.append((name, np.dtype(sub)))
            names.extend(sub_names)
    return dtype, names


def state_record(fields) -> tuple[np.dtype, tuple[str, ...]]:
    """``(dtype, state_names)`` of a filter's state from its fields after the common
    ``state[0:5]`` (``quat`` (4,), ``initialized``): each field is ``(name, spec)`` with ``spec``
    the flat name of one float, a tuple of flat names (a float64 vector, or a matrix for a tuple
    of tuples) or a list of fields (a nested record). ``dtype`` (float64 throughout, packed in
    field order) lays out the whole flat state, so a kernel reads ``state.view(dtype)[0]``;
    ``state_names`` are the flat names of ``state[5:]`` in the same order."""
    dtype, names = _record_layout(COMMON_STATE_FIELDS + tuple(fields))
    dtype = np.dtype(dtype)
    return dtype, tuple(names[N_COMMON_STATE:])


def record_view(dtype: np.dtype):
    """A numba function ``view(state) -> record``: the flat float64 ``state`` ``(n,)`` read as one
    record of the structured ``dtype`` (``state_record``), in place (writes go to ``state``). The
    same as ``state.view(dtype)[0]`` without a new array and its reference count per call (a cost
    paid every sample). Unchecked: ``state`` must be C-contiguous and hold at
    least ``dtype.itemsize`` bytes, as a filter's state does (``OrientationFilter``)."""
    record = numba.from_dtype(dtype)

    @intrinsic
    def view(typingctx, state):
        if not (isinstance(state, types.Array) and state.dtype == types.float64 and state.ndim == 1):
            return None

        def codegen(context, builder, signature, args):
            data = context.make_array(signature.args[0])(context, builder, args[0]).data
            return builder.bitcast(data, context.get_value_type(record))
        return record(state), codegen
    return view


def record_of(state: np.ndarray, dtype: np.dtype):
    """In Python: the flat float64 ``state`` ``(n,)`` as one record of the structured ``dtype``
    (``state_record``; fields by name, e.g. ``record_of(f.state, f.state_dtype).bias``): a view,
    writes go to ``state``."""
    return state.view(dtype).view(np.recarray)[0]


def record_fields(record: type, prefix: str) -> list:
    """The ``state_record`` fields that hold a ``NamedTuple`` of floats (nested ones as nested
    records), flat names ``prefix + field`` (``_`` between nested names): the record's field
    order, written once in its class."""
    hints = get_type_hints(record)
    return [(f, record_fields(hints[f], f"{prefix}{f}_")) if _is_record(hints[f]) else (f, f"{prefix}{f}")
            for f in record._fields]


@dataclass
class FilterOutput:
    """Result of ``update_batch``.

    Attributes:
        quat: ``(N, 4)`` orientation, sensor -> ENU.
        diagnostics: name -> ``(N,)`` array (gain used, flags, bias estimates, ...).
    """

    quat: np.ndarray
    diagnostics: dict

    def in_frame(self, frame: str) -> np.ndarray:
        """``quat`` expressed w.r.t. another earth frame (``'NED'``, ``'NWU'``, ``'ENU'``)."""
        return to_frame(self.quat, frame)


@njit(cache=False)
def run_batch(step, state, params, gyr, acc, mag, dt, quat_out, diag_out):
    """The one batch loop: ``step`` over all samples, recording the quaternion after each."""
    for i in range(gyr.shape[0]):
        step(state, params, gyr[i], acc[i], mag[i], dt[i], diag_out[i])
        quat_out[i, 0] = state[0]
        quat_out[i, 1] = state[1]
        quat_out[i, 2] = state[2]
        quat_out[i, 3] = state[3]


def dt_from_timestamps(t) -> np.ndarray:
    """Per-sample time steps [s] ``(N,)`` from timestamps [s]; the first sample gets the
    median step (it is only used for the first propagation, which is skipped anyway)."""
    t = np.asarray(t, dtype=np.float64)
    if t.ndim != 1 or t.size < 2:
        raise ValueError(f"timestamps: expected shape (N,) with N >= 2, got {t.shape}")
    dt = np.diff(t, prepend=np.nan)
    dt[0] = np.nanmedian(dt[1:])
    return dt


class OrientationFilter:
    """Base class. Subclasses set ``name``, ``Settings``, ``Coefficients``, ``state_names``,
    ``diagnostic_names``, ``step`` and implement ``_coefficients``."""

    name: ClassVar[str] = ""
    Settings: ClassVar[type] = FilterSettings
    #: the ``params`` record: a ``NamedTuple`` starting with ``use_mag, max_dt`` (module docstring)
    Coefficients: ClassVar[type] = CommonCoefficients
    #: names of ``state[5:]``
    state_names: ClassVar[tuple[str, ...]] = ()
    diagnostic_names: ClassVar[tuple[str, ...]] = ()
    step: ClassVar = None  # numba dispatcher

    def __init_subclass__(cls, **kwargs):
        super().__init_subclass__(**kwargs)
        if tuple(getattr(cls.Coefficients, "_fields", ()))[:2] != COMMON_COEFFICIENTS:
            raise TypeError(f"{cls.__name__}.Coefficients must be a NamedTuple whose first fields are "
                            f"{COMMON_COEFFICIENTS}")

    def __init__(self, fs: float, settings=None, *, use_mag: bool = True, **overrides):
        """Args:
            fs: sampling rate [Hz] (required: there is no default rate).
            settings: a ``Settings`` instance; keyword ``overrides`` replace its fields.
            use_mag: 9D (True) or 6D (False, the magnetometer is ignored).
        """
        if fs is None or not (isinstance(fs, (int, float, np.floating)) and math.isfinite(fs) and fs > 0):
            raise ValueError(f"{type(self).__name__}: fs must be a positive sampling rate in Hz, got {fs!r}")
        self.fs = float(fs)
        self.Ts = 1.0 / self.fs
        settings = settings if settings is not None else self.Settings()
        if not isinstance(settings, self.Settings):
            raise TypeError(f"settings must be {self.Settings.__name__}, got {type(settings).__name__}")
        known = {f.name for f in fields(self.Settings)}
        unknown = set(overrides) - known
        if unknown:
            raise TypeError(f"{type(self).__name__}: unknown setting(s) {sorted(unknown)}; known: {sorted(known)}")
        self.settings = replace(settings, **overrides)
        self.use_mag = bool(use_mag)
        self.params = make_coefficients(self.Coefficients, use_mag=1.0 if self.use_mag else 0.0,
                                        max_dt=self.settings.max_dt, **self._coefficients())
        self.state = np.zeros(N_COMMON_STATE + len(self.state_names))
        self.reset()
        self._diag = np.zeros(len(self.diagnostic_names))

    # -- to be provided by subclasses ------------------------------------------------------------
    def _coefficients(self) -> dict:
        """The filter's own ``Coefficients`` fields (all but ``use_mag``, ``max_dt``) by name,
        from ``self.settings`` and ``self.Ts``."""
        raise NotImplementedError

    # -- state ---------------------------------------------------------------------------------
    def reset(self):
        """Forget everything: the next valid sample initialises the orientation."""
        self.state[:] = 0.0
        self.state[0] = 1.0

    def get_state(self) -> np.ndarray:
        """A copy of the full state vector (see ``state_dict`` for names)."""
        return self.state.copy()

    def set_state(self, state):
        state = np.asarray(state, dtype=np.float64)
        if state.shape != self.state.shape:
            raise ValueError(f"{type(self).__name__}: state must have shape {self.state.shape}, got {state.shape}")
        self.state[:] = state

    def state_dict(self) -> dict:
        """The state by name: ``quat``, ``initialized`` and the filter's own entries."""
        d = {"quat": self.state[:4].copy(), "initialized": bool(self.state[4] > 0.5)}
        d.update({n: float(self.state[N_COMMON_STATE + i]) for i, n in enumerate(self.state_names)})
        return d

    def set_quat(self, q):
        """Set the orientation (sensor -> ENU) and mark the filter initialised."""
        q = np.asarray(q, dtype=np.float64).reshape(4)
        if not np.all(np.isfinite(q)) or np.linalg.norm(q) < 1e-9:
            raise ValueError(f"initial quaternion must be finite and non-zero, got {q}")
        self.state[:4] = q / np.linalg.norm(q)
        self.state[4] = 1.0

    @property
    def quat(self) -> np.ndarray:
        """Current orientation ``(4,)``, sensor -> ENU."""
        return self.state[:4].copy()

    # -- running ---------------------------------------------------------------------------------
    def update(self, gyr, acc, mag=None, dt=None) -> np.ndarray:
        """One sample: gyr [rad/s], acc [m/s²], mag (any unit; ignored in 6D), each ``(3,)``;
        ``dt`` [s] defaults to ``Ts``. Returns the new orientation ``(4,)``; the diagnostics
        of this sample are in ``last_diagnostics``."""
        g = _vec3(gyr, "gyr")
        a = _vec3(acc, "acc")
        m = _vec3(mag, "mag") if mag is not None else np.zeros(3)
        if mag is None and self.use_mag:
            raise ValueError(f"{type(self).__name__} is in 9D mode: pass mag, or construct with use_mag=False")
        type(self).step(self.state, self.params, g, a, m, self.Ts if dt is None else float(dt), self._diag)
        return self.quat

    @property
    def last_diagnostics(self) -> dict:
        return dict(zip(self.diagnostic_names, self._diag.tolist()))

    def batch_inputs(self, gyr, acc, mag, dt):
        """The inputs of ``update_batch`` validated for this filter: contiguous float64 ``(N, 3)`` gyr,
        acc, mag (zeros in 6D) and ``(N,)`` dt [s] (``Ts`` when ``dt`` is None)."""
        gyr = _series(gyr, "gyr")
        n = gyr.shape[0]
        acc = _series(acc, "acc", n)
        if mag is None:
            if self.use_mag:
                raise ValueError(f"{type(self).__name__} is in 9D mode: pass mag, or construct with use_mag=False")
            mag = np.zeros((n, 3))
        else:
            mag = _series(mag, "mag", n)
        if dt is None:
            dt = np.full(n, self.Ts)
        else:
            dt = np.asarray(dt, dtype=np.float64)
            dt = np.full(n, float(dt)) if dt.ndim == 0 else np.ascontiguousarray(dt)
            if dt.shape != (n,):
                raise ValueError(f"dt: expected a scalar or shape ({n},), got {dt.shape}")
        return gyr, acc, mag, dt

    def update_batch(self, gyr, acc, mag=None, dt=None) -> FilterOutput:
        """Arrays ``(N, 3)`` (see ``update``); ``dt`` a scalar or ``(N,)`` per-sample steps [s]
        (``dt_from_timestamps`` makes them from timestamps). Continues from the current state."""
        gyr, acc, mag, dt = self.batch_inputs(gyr, acc, mag, dt)
        n = gyr.shape[0]
        quat_out = np.empty((n, 4))
        diag_out = np.zeros((n, len(self.diagnostic_names)))
        run_batch(type(self).step, self.state, self.params, gyr, acc, mag, dt, quat_out, diag_out)
        if n:
            self._diag[:] = diag_out[-1]
        return FilterOutput(quat_out, {k: diag_out[:, i] for i, k in enumerate(self.diagnostic_names)})

    def __repr__(self):
        return f"{type(self).__name__}(fs={self.fs:g}, {'9D' if self.use_mag else '6D'}, {self.settings})"


def _vec3(v, name):
    v = np.asarray(v, dtype=np.float64)
    if v.shape != (3,):
        raise ValueError(f"{name}: expected shape (3,), got {v.shape}")
    return v


def _series(v, name, n=None):
    v = np.ascontiguousarray(v, dtype=np.float64)
    if v.ndim != 2 or v.shape[1] != 3:
        raise ValueError(f"{name}: expected shape (N, 3), got {v.shape}")
    if n is not None and v.shape[0] != n:
        raise ValueError(f"{name}: has {v.shape[0]} samples, gyr has {n}")
    return v


# ------------------------------------------------------------------------------------------
# Numba building blocks shared by the filter kernels
# ------------------------------------------------------------------------------------------

@njit(cache=True, inline="always")
def vector_ok(v):
    """True for a finite, non-zero 3-vector."""
    n2 = v[0] * v[0] + v[1] * v[1] + v[2] * v[2]
    return math.isfinite(n2) and n2 > 1e-18


@njit(cache=True, inline="always")
def field_agrees(ref_norm, ref_dip, norm, dip, norm_th, dip_th):
    """VQF's magnetic disturbance test (its M2/M3): the field's norm within ``norm_th`` of ``ref_norm``
    (relative) and its dip [rad] within ``dip_th`` of ``ref_dip``."""
    return abs(norm - ref_norm) < norm_th * ref_norm and abs(dip - ref_dip) < dip_th


@njit(cache=True, inline="always")
def gyro_valid(gyr):
    """True for a usable gyro sample: every axis finite and below ``GYRO_FULL_SCALE`` (policy above)."""
    # False for NaN too (comparisons with NaN are False). `&`, not `and`: the short-circuit form's
    # branches, inlined into gyro_increment, are slower than three comparisons (bench_filters).
    return (abs(gyr[0]) < GYRO_FULL_SCALE) & (abs(gyr[1]) < GYRO_FULL_SCALE) & (abs(gyr[2]) < GYRO_FULL_SCALE)


@njit(cache=True, inline="always")
def dt_valid(dt, max_dt):
    """True for a Δt [s] that is integrated: finite, > 0 and <= ``max_dt`` (policy above)."""
    return math.isfinite(dt) & (dt > 0.0) & (dt <= max_dt)  # `&`: see gyro_valid


@njit(cache=True, inline="always")
def gyro_increment(gyr, dt, max_dt):
    """``exp(ω Δt / 2)`` of one gyro sample [rad/s] over Δt [s]: ``(ok, dq)``, with ``ok`` False
    (and ``dq`` identity) for a non-finite or saturated ω or an invalid Δt (policy above)."""
    if not gyro_valid(gyr):
        return False, (1.0, 0.0, 0.0, 0.0)
    if not dt_valid(dt, max_dt):
        return False, (1.0, 0.0, 0.0, 0.0)
    return True, from_rotvec_scalar(gyr[0] * dt, gyr[1] * dt, gyr[2] * dt)


@njit(cache=True, inline="always")
def propagate_gyro(q, gyr, dt, max_dt):
    """``q ⊗ exp(ω Δt / 2)``: strapdown integration of one gyro sample [rad/s] over Δt [s].

    Returns ``(q_new, done)``; skipped (q unchanged) for non-finite or saturated ω or an invalid Δt.
    """
    ok, dq = gyro_increment(gyr, dt, max_dt)
    if not ok:
        return q, False
    return normalize_scalar(multiply_scalar(q, dq)), True


@njit(cache=True, inline="always")
def acc_mag_quaternion(q_ref, acc, mag, mag_ok):
    """Orientation measured by acc and mag (9D, ``from_acc_mag``), or, when the magnetometer
    is not used or not valid, ``q_ref`` corrected by the shortest earth-frame rotation that
    takes its predicted up direction onto the measured one (6D: a pure tilt correction with
    zero vertical component, as Valenti et al.'s Δq_acc, eq. 25). Returned in the hemisphere
    of ``q_ref`` so that LERP/SLERP between the two takes the short arc. Returns ``(ok, q)``."""
    if mag_ok:
        ok, q = from_acc_mag_scalar(acc[0], acc[1], acc[2], mag[0], mag[1], mag[2])
    else:
        na = math.sqrt(acc[0] * acc[0] + acc[1] * acc[1] + acc[2] * acc[2])
        ok = na > 1e-9
        g = rotate_scalar(q_ref, (acc[0] / na, acc[1] / na, acc[2] / na)) if ok else (0.0, 0.0, 1.0)
        if 1.0 + g[2] > 1e-9:
            dq = normalize_scalar((1.0 + g[2], g[1], -g[0], 0.0))  # rotation taking g onto +z
        else:  # measured up is predicted down: any horizontal axis will do
            dq = (0.0, 1.0, 0.0, 0.0)
        q = multiply_scalar(dq, q_ref)
    if q[0] * q_ref[0] + q[1] * q_ref[1] + q[2] * q_ref[2] + q[3] * q_ref[3] < 0.0:
        q = (-q[0], -q[1], -q[2], -q[3])
    return ok, q


@njit(cache=True, inline="always")
def initialize_from_sample(state, acc, mag, mag_ok):
    """Set ``state[0:4]`` from the first valid acc(/mag) sample (heading 0 in 6D). Returns ok."""
    ok, q = acc_mag_quaternion((1.0, 0.0, 0.0, 0.0), acc, mag, mag_ok)
    if ok:
        state[0], state[1], state[2], state[3] = q
        state[4] = 1.0
    return ok


@njit(cache=True, inline="always")
def load_quat(v):
    """The quaternion in ``v[0:4]`` (a filter's state, or a quaternion field of a state record) as a 4-tuple."""
    return (v[0], v[1], v[2], v[3])


@njit(cache=True, inline="always")
def store_quat(v, q):
    """Write the 4-tuple ``q`` into ``v[0:4]``."""
    v[0], v[1], v[2], v[3] = q
