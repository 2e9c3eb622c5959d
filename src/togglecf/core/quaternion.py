"""Quaternion maths: the project's one statement of its conventions.

Conventions (used everywhere in togglecf):

* A quaternion is ``[w, x, y, z]`` (scalar first), float64, Hamilton product
  (``i*j = k``), a unit quaternion is a rotation.
* An orientation quaternion ``q`` maps sensor-frame vectors to the earth frame:
  ``v_earth = q ⊗ [0, v_sensor] ⊗ q*``  (``rotate(q, v)``).
* The earth frame is **ENU**: x east, y north, z up. Other frames (NED, NWU) are
  converted at the boundary with the fixed quaternions below.
* Time series are ``(N, 4)`` / ``(N, 3)`` arrays, one sample a row. Every vectorised
  function here accepts any leading shape ``(..., 4)``.

Two layers:

* numpy functions (``multiply``, ``rotate``, ...), vectorised over leading axes;
* ``*_scalar`` numba functions on 4-/3-tuples of floats for filter kernels. They
  allocate nothing and are meant to be called from other ``@njit`` code.
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit

__all__ = [
    "IDENTITY", "ENU_FROM_NWU", "ENU_FROM_NED",
    "as_quat", "normalize", "multiply", "conjugate", "rotate", "to_matrix", "from_matrix",
    "from_rotvec", "to_rotvec", "lerp", "slerp", "to_euler_zyx", "from_euler_zyx",
    "from_acc_mag", "from_acc", "angle_between", "to_frame", "from_frame",
]

IDENTITY = np.array([1.0, 0.0, 0.0, 0.0])
_S45 = math.sqrt(0.5)
#: ``q_enu = ENU_FROM_NWU ⊗ q_nwu``: +90° about the vertical (NWU x=north -> ENU y=north).
ENU_FROM_NWU = np.array([_S45, 0.0, 0.0, _S45])
#: ``q_enu = ENU_FROM_NED ⊗ q_ned``: NED x=north,y=east,z=down -> ENU; 180° about (1,1,0)/√2.
ENU_FROM_NED = np.array([0.0, _S45, _S45, 0.0])
_FRAMES = {"ENU": IDENTITY, "NWU": ENU_FROM_NWU, "NED": ENU_FROM_NED}

_EPS = 1e-12


def as_quat(q, name: str = "quaternion") -> np.ndarray:
    """Return ``q`` as a float64 array of shape ``(..., 4)``; raise ``ValueError`` otherwise."""
    q = np.asarray(q, dtype=np.float64)
    if q.ndim == 0 or q.shape[-1] != 4:
        raise ValueError(f"{name}: expected shape (..., 4), got {q.shape}")
    return q


def _as_vec(v, name: str = "vector") -> np.ndarray:
    v = np.asarray(v, dtype=np.float64)
    if v.ndim == 0 or v.shape[-1] != 3:
        raise ValueError(f"{name}: expected shape (..., 3), got {v.shape}")
    return v


def normalize(q) -> np.ndarray:
    """Unit quaternion(s) ``(..., 4)``; zero-norm rows become NaN rather than dividing by zero."""
    q = as_quat(q)
    n = np.linalg.norm(q, axis=-1, keepdims=True)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(n > _EPS, q / np.where(n > _EPS, n, 1.0), np.nan)


def multiply(p, q) -> np.ndarray:
    """Hamilton product ``p ⊗ q`` (broadcast over leading axes)."""
    p, q = as_quat(p, "p"), as_quat(q, "q")
    pw, px, py, pz = np.moveaxis(p, -1, 0)
    qw, qx, qy, qz = np.moveaxis(q, -1, 0)
    return np.stack([
        pw * qw - px * qx - py * qy - pz * qz,
        pw * qx + px * qw + py * qz - pz * qy,
        pw * qy - px * qz + py * qw + pz * qx,
        pw * qz + px * qy - py * qx + pz * qw,
    ], axis=-1)


def conjugate(q) -> np.ndarray:
    """Conjugate ``[w, -x, -y, -z]`` (the inverse of a unit quaternion)."""
    q = as_quat(q)
    return q * np.array([1.0, -1.0, -1.0, -1.0])


def rotate(q, v) -> np.ndarray:
    """Rotate vectors ``v (..., 3)`` by unit quaternions ``q (..., 4)``: sensor -> earth."""
    q, v = as_quat(q), _as_vec(v)
    w = q[..., :1]
    u = q[..., 1:]
    t = 2.0 * np.cross(u, v)  # v' = v + w t + u x t  (Rodrigues in quaternion form)
    return v + w * t + np.cross(u, t)


def to_matrix(q) -> np.ndarray:
    """Rotation matrices ``(..., 3, 3)`` of unit quaternions: ``v_earth = R @ v_sensor``."""
    w, x, y, z = np.moveaxis(as_quat(q), -1, 0)
    return np.stack([
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
        np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
        np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
    ], axis=-2)


def from_matrix(R) -> np.ndarray:
    """Unit quaternions ``(..., 4)`` with ``w >= 0`` from rotation matrices ``(..., 3, 3)``.

    Shepperd's method: use the largest of w², x², y², z² as pivot, stable near 180°.
    """
    R = np.asarray(R, dtype=np.float64)
    if R.shape[-2:] != (3, 3):
        raise ValueError(f"rotation matrix: expected shape (..., 3, 3), got {R.shape}")
    r00, r11, r22 = R[..., 0, 0], R[..., 1, 1], R[..., 2, 2]
    tr = r00 + r11 + r22
    cands = np.stack([
        np.stack([1 + tr, R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0], R[..., 1, 0] - R[..., 0, 1]], -1),
        np.stack([R[..., 2, 1] - R[..., 1, 2], 1 + r00 - r11 - r22, R[..., 0, 1] + R[..., 1, 0], R[..., 0, 2] + R[..., 2, 0]], -1),
        np.stack([R[..., 0, 2] - R[..., 2, 0], R[..., 0, 1] + R[..., 1, 0], 1 - r00 + r11 - r22, R[..., 1, 2] + R[..., 2, 1]], -1),
        np.stack([R[..., 1, 0] - R[..., 0, 1], R[..., 0, 2] + R[..., 2, 0], R[..., 1, 2] + R[..., 2, 1], 1 - r00 - r11 + r22], -1),
    ], axis=-2)  # row k is 4*q_k*q for pivot k
    pivot = np.argmax(np.stack([tr, r00, r11, r22], -1), axis=-1)
    q = np.take_along_axis(cands, pivot[..., None, None], axis=-2)[..., 0, :]
    q = normalize(q)
    return np.where(q[..., :1] < 0, -q, q)


def from_rotvec(rotvec) -> np.ndarray:
    """Exponential map: rotation vectors ``(..., 3)`` [rad] -> unit quaternions."""
    r = _as_vec(rotvec, "rotation vector")
    angle = np.linalg.norm(r, axis=-1, keepdims=True)
    half = 0.5 * angle
    # sin(a/2)/a, with its Taylor series for tiny angles to avoid 0/0
    small = angle < 1e-6
    k = np.where(small, 0.5 - angle**2 / 48.0, np.sin(half) / np.where(small, 1.0, angle))
    return np.concatenate([np.cos(half), k * r], axis=-1)


def to_rotvec(q) -> np.ndarray:
    """Logarithm map: unit quaternions -> rotation vectors ``(..., 3)`` [rad], angle in [0, π]."""
    q = normalize(q)
    q = np.where(q[..., :1] < 0, -q, q)
    v = q[..., 1:]
    s = np.linalg.norm(v, axis=-1, keepdims=True)
    angle = 2.0 * np.arctan2(s, q[..., :1])
    small = s < 1e-9
    k = np.where(small, 2.0 / np.where(small, q[..., :1], 1.0), angle / np.where(small, 1.0, s))
    return k * v


def lerp(p, q, t) -> np.ndarray:
    """Normalised linear interpolation ``(1-t) p + t q`` along the shorter arc."""
    p, q = as_quat(p, "p"), as_quat(q, "q")
    t = np.asarray(t, dtype=np.float64)[..., None]
    q = np.where(np.sum(p * q, axis=-1, keepdims=True) < 0, -q, q)
    return normalize((1.0 - t) * p + t * q)


def slerp(p, q, t) -> np.ndarray:
    """Spherical linear interpolation from ``p`` (t=0) to ``q`` (t=1) along the shorter arc."""
    p, q = normalize(p), normalize(q)
    t = np.asarray(t, dtype=np.float64)[..., None]
    d = np.sum(p * q, axis=-1, keepdims=True)
    q = np.where(d < 0, -q, q)
    d = np.abs(d)
    theta = np.arccos(np.clip(d, -1.0, 1.0))
    near = theta < 1e-6  # sin(theta) ~ 0: LERP is exact to machine precision there
    s = np.sin(np.where(near, 1.0, theta))
    wp = np.where(near, 1.0 - t, np.sin((1.0 - t) * theta) / s)
    wq = np.where(near, t, np.sin(t * theta) / s)
    return normalize(wp * p + wq * q)


def to_euler_zyx(q) -> np.ndarray:
    """Roll, pitch, yaw [rad] ``(..., 3)`` with ``R = Rz(yaw) Ry(pitch) Rx(roll)``.

    Equals scipy's ``Rotation.as_euler('ZYX')[..., ::-1]``. At gimbal lock (|pitch| = 90°)
    roll is set to 0 and the whole rotation about the vertical goes into yaw (scipy's choice).
    """
    R = to_matrix(normalize(q))
    sp = np.clip(-R[..., 2, 0], -1.0, 1.0)
    pitch = np.arcsin(sp)
    lock = np.abs(sp) > 1.0 - 1e-10
    roll = np.where(lock, 0.0, np.arctan2(R[..., 2, 1], R[..., 2, 2]))
    yaw = np.where(lock, np.arctan2(-R[..., 0, 1], R[..., 1, 1]), np.arctan2(R[..., 1, 0], R[..., 0, 0]))
    return np.stack([roll, pitch, yaw], axis=-1)


def from_euler_zyx(rpy) -> np.ndarray:
    """Unit quaternions from roll, pitch, yaw [rad] ``(..., 3)``, inverse of ``to_euler_zyx``."""
    rpy = _as_vec(rpy, "roll/pitch/yaw")
    half = 0.5 * rpy
    c, s = np.cos(half), np.sin(half)
    cr, cp, cy = c[..., 0], c[..., 1], c[..., 2]
    sr, sp, sy = s[..., 0], s[..., 1], s[..., 2]
    return np.stack([
        cy * cp * cr + sy * sp * sr,
        cy * cp * sr - sy * sp * cr,
        cy * sp * cr + sy * cp * sr,
        sy * cp * cr - cy * sp * sr,
    ], axis=-1)


def from_acc_mag(acc, mag) -> np.ndarray:
    """Orientation (sensor -> ENU) from accelerometer ``(..., 3)`` and magnetometer ``(..., 3)``.

    At rest the accelerometer measures +g along earth-up, so ``up = acc/|acc|``;
    ``east = mag × up`` (the magnetometer's vertical part drops out); ``north = up × east``.
    The rows of R (sensor -> earth) are east, north, up in sensor coordinates. Units of
    ``mag`` do not matter; degenerate inputs (zero norm, mag ∥ acc) give NaN.
    """
    a, m = _as_vec(acc, "acc"), _as_vec(mag, "mag")
    with np.errstate(invalid="ignore", divide="ignore"):
        up = a / np.linalg.norm(a, axis=-1, keepdims=True)
        east = np.cross(m, up)
        east = east / np.linalg.norm(east, axis=-1, keepdims=True)
        north = np.cross(up, east)
        R = np.stack([east, north, up], axis=-2)
        bad = ~np.all(np.isfinite(R), axis=(-2, -1))
        q = from_matrix(np.where(bad[..., None, None], np.eye(3), R))
    return np.where(bad[..., None], np.nan, q)


def from_acc(acc) -> np.ndarray:
    """Tilt-only orientation (heading zero, shortest rotation taking ``acc`` to earth-up)."""
    a = _as_vec(acc, "acc")
    with np.errstate(invalid="ignore", divide="ignore"):
        up = a / np.linalg.norm(a, axis=-1, keepdims=True)
    # rotation of `up` onto z: q = normalize([1 + up_z, up_y, -up_x, 0]); singular only for up = -z
    q = np.stack([1.0 + up[..., 2], up[..., 1], -up[..., 0], np.zeros_like(up[..., 0])], -1)
    flip = (1.0 + up[..., 2]) < 1e-9
    q = np.where(flip[..., None], np.array([0.0, 1.0, 0.0, 0.0]), q)
    return normalize(q)


def angle_between(p, q) -> np.ndarray:
    """Rotation angle [rad] of ``p ⊗ q*``, in [0, π]. Uses atan2, accurate near 0 where
    arccos of the dot product loses half the digits (~1e-8 rad floor)."""
    r = multiply(normalize(p), conjugate(normalize(q)))
    return 2.0 * np.arctan2(np.linalg.norm(r[..., 1:], axis=-1), np.abs(r[..., 0]))


def to_frame(q_enu, frame: str) -> np.ndarray:
    """Convert ENU orientations to another earth frame: ``'ENU'``, ``'NED'`` or ``'NWU'``."""
    return multiply(conjugate(_frame(frame)), as_quat(q_enu))


def from_frame(q, frame: str) -> np.ndarray:
    """Convert orientations given w.r.t. earth frame ``frame`` (ENU, NED, NWU) to ENU."""
    return multiply(_frame(frame), as_quat(q))


def _frame(frame: str) -> np.ndarray:
    try:
        return _FRAMES[frame.upper()]
    except (KeyError, AttributeError):
        raise ValueError(f"unknown earth frame {frame!r}; expected one of {sorted(_FRAMES)}") from None


# ---------------------------------------------------------------------------------------------
# Scalar numba versions for filter kernels. Quaternions are 4-tuples (w, x, y, z), vectors 3-tuples.
# ---------------------------------------------------------------------------------------------

@njit(cache=True, inline="always")
def multiply_scalar(p, q):
    """Hamilton product of two 4-tuples."""
    return (p[0] * q[0] - p[1] * q[1] - p[2] * q[2] - p[3] * q[3],
            p[0] * q[1] + p[1] * q[0] + p[2] * q[3] - p[3] * q[2],
            p[0] * q[2] - p[1] * q[3] + p[2] * q[0] + p[3] * q[1],
            p[0] * q[3] + p[1] * q[2] - p[2] * q[1] + p[3] * q[0])


@njit(cache=True, inline="always")
def conjugate_scalar(q):
    return (q[0], -q[1], -q[2], -q[3])


@njit(cache=True, inline="always")
def normalize_scalar(q):
    """Unit 4-tuple; returns identity for a zero or non-finite input (callers check first)."""
    n = math.sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3])
    if not (n > 1e-12) or not math.isfinite(n):
        return (1.0, 0.0, 0.0, 0.0)
    return (q[0] / n, q[1] / n, q[2] / n, q[3] / n)


@njit(cache=True, inline="always")
def rotate_scalar(q, v):
    """Rotate 3-tuple ``v`` from sensor to earth by unit 4-tuple ``q``."""
    w, x, y, z = q
    tx = 2.0 * (y * v[2] - z * v[1])
    ty = 2.0 * (z * v[0] - x * v[2])
    tz = 2.0 * (x * v[1] - y * v[0])
    return (v[0] + w * tx + y * tz - z * ty,
            v[1] + w * ty + z * tx - x * tz,
            v[2] + w * tz + x * ty - y * tx)


@njit(cache=True, inline="always")
def rotate_inverse_scalar(q, v):
    """Rotate 3-tuple ``v`` from earth to sensor (by ``q*``)."""
    return rotate_scalar((q[0], -q[1], -q[2], -q[3]), v)


@njit(cache=True, inline="always")
def from_rotvec_scalar(rx, ry, rz):
    """Exponential map of a rotation vector [rad] to a unit 4-tuple."""
    angle = math.sqrt(rx * rx + ry * ry + rz * rz)
    if angle < 1e-6:
        k = 0.5 - angle * angle / 48.0
    else:
        k = math.sin(0.5 * angle) / angle
    return (math.cos(0.5 * angle), k * rx, k * ry, k * rz)


@njit(cache=True, inline="always")
def from_matrix_scalar(r00, r01, r02, r10, r11, r12, r20, r21, r22):
    """Shepperd's method on a row-major rotation matrix; returns a unit 4-tuple with w >= 0."""
    tr = r00 + r11 + r22
    if tr >= r00 and tr >= r11 and tr >= r22:
        q = (1.0 + tr, r21 - r12, r02 - r20, r10 - r01)
    elif r00 >= r11 and r00 >= r22:
        q = (r21 - r12, 1.0 + r00 - r11 - r22, r01 + r10, r02 + r20)
    elif r11 >= r22:
        q = (r02 - r20, r01 + r10, 1.0 - r00 + r11 - r22, r12 + r21)
    else:
        q = (r10 - r01, r02 + r20, r12 + r21, 1.0 - r00 - r11 + r22)
    q = normalize_scalar(q)
    if q[0] < 0.0:
        return (-q[0], -q[1], -q[2], -q[3])
    return q


@njit(cache=True, inline="always")
def from_acc_mag_scalar(ax, ay, az, mx, my, mz):
    """Sensor -> ENU orientation from one acc and one mag sample (see ``from_acc_mag``).

    Returns ``(ok, q)``; ``ok`` is False for zero-norm or parallel inputs, and ``q`` is then identity.
    """
    na = math.sqrt(ax * ax + ay * ay + az * az)
    if not (na > 1e-9):
        return False, (1.0, 0.0, 0.0, 0.0)
    ux, uy, uz = ax / na, ay / na, az / na
    ex, ey, ez = my * uz - mz * uy, mz * ux - mx * uz, mx * uy - my * ux  # east = mag x up
    ne = math.sqrt(ex * ex + ey * ey + ez * ez)
    if not (ne > 1e-9):
        return False, (1.0, 0.0, 0.0, 0.0)
    ex, ey, ez = ex / ne, ey / ne, ez / ne
    nx, ny, nz = uy * ez - uz * ey, uz * ex - ux * ez, ux * ey - uy * ex  # north = up x east
    return True, from_matrix_scalar(ex, ey, ez, nx, ny, nz, ux, uy, uz)
