"""Synthetic IMU with exact ground truth, for testing the maths.

``imu_from_orientation`` turns an orientation trajectory (sensor -> ENU) into gyro, acc and
mag signals. The gyro is the exact body rate between consecutive samples,
``ω_k = log(q_k* ⊗ q_{k+1}) / Δt``, so strapdown integration of noiseless data reproduces
the trajectory to rounding error. Output is a ``Trial`` so every tool runs on it.
"""
from __future__ import annotations

import numpy as np

from togglecf.core import quaternion as quat
from togglecf.data.broad import GRAVITY, Trial, write_broad_hdf5  # noqa: F401 (in __all__)

__all__ = ["EARTH_MAG_ENU", "imu_from_orientation", "static_trajectory", "axis_sweep_trajectory",
           "random_smooth_trajectory", "gimbal_trajectory", "turntable_trajectory", "random_walk_bias",
           "linear_acceleration_bursts", "vibration", "mag_disturbance_intervals", "rest_then_motion_trajectory",
           "translation_moves", "taps", "write_broad_hdf5"]

#: Earth field in ENU [µT]: 49 µT with 67° dip, close to Berlin's (where BROAD was recorded).
EARTH_MAG_ENU = 49.0 * np.array([0.0, np.cos(np.radians(67.0)), -np.sin(np.radians(67.0))])


def imu_from_orientation(q, fs: float, *, gyro_noise: float = 0.0, acc_noise: float = 0.0,
                         mag_noise: float = 0.0, gyro_bias=(0.0, 0.0, 0.0),
                         lin_acc_earth=None, mag_disturbance_earth=None, mag_earth=EARTH_MAG_ENU,
                         seed: int = 0) -> Trial:
    """IMU signals for orientations ``q (N, 4)`` at ``fs`` [Hz], as a ``Trial`` named ``"synthetic"`` (another
    name: ``dataclasses.replace(trial, name=...)``).

    Args:
        gyro_noise: white-noise standard deviation of the gyro [rad/s].
        acc_noise: white-noise standard deviation of the accelerometer [m/s²].
        mag_noise: white-noise standard deviation of the magnetometer [µT].
        gyro_bias: gyro bias [rad/s] (sensor frame): constant ``(3,)`` or per sample ``(N, 3)``
            (e.g. from ``random_walk_bias``).
        lin_acc_earth: ``(N, 3)`` linear acceleration of the sensor in ENU [m/s²], optional
            (``linear_acceleration_bursts``, ``vibration``, or their sum).
        mag_disturbance_earth: ``(N, 3)`` field added to ``mag_earth`` in ENU [µT], optional
            (``mag_disturbance_intervals``).
        seed: noise seed (runs are deterministic).
    """
    q = quat.normalize(quat.as_quat(q))
    n = q.shape[0]
    dt = 1.0 / fs
    rng = np.random.default_rng(seed)
    dq = quat.multiply(quat.conjugate(q[:-1]), q[1:])
    gyr = np.empty((n, 3))
    gyr[:-1] = quat.to_rotvec(dq) / dt  # rate applied from sample k to k+1
    gyr[-1] = gyr[-2] if n > 1 else 0.0
    # the filter propagates with the gyro sample that arrives *with* q_k, so shift by one
    gyr = np.roll(gyr, 1, axis=0)
    gyr[0] = 0.0
    f_earth = np.tile([0.0, 0.0, GRAVITY], (n, 1))  # specific force at rest points up
    if lin_acc_earth is not None:
        f_earth = f_earth + np.asarray(lin_acc_earth, float)
    m_earth = np.tile(np.asarray(mag_earth, float), (n, 1))
    if mag_disturbance_earth is not None:
        m_earth = m_earth + np.asarray(mag_disturbance_earth, float)
    q_inv = quat.conjugate(q)
    acc = quat.rotate(q_inv, f_earth)
    mag = quat.rotate(q_inv, m_earth)
    gyr = gyr + np.asarray(gyro_bias, float) + gyro_noise * rng.standard_normal((n, 3))
    acc = acc + acc_noise * rng.standard_normal((n, 3))
    mag = mag + mag_noise * rng.standard_normal((n, 3))
    return Trial(name="synthetic", fs=fs, gyr=gyr, acc=acc, mag=mag, opt_quat=q, opt_pos=np.zeros((n, 3)),
                 movement=np.ones(n, bool))


def static_trajectory(rpy_deg, n: int) -> np.ndarray:
    """``(n, 4)`` constant orientation from roll, pitch, yaw in degrees."""
    return np.tile(quat.from_euler_zyx(np.radians(rpy_deg)), (n, 1))


def axis_sweep_trajectory(axis, angle_deg: float, fs: float, duration: float, start=quat.IDENTITY) -> np.ndarray:
    """Smooth sweep (raised-cosine profile) of ``angle_deg`` about a body ``axis`` over ``duration`` [s]."""
    n = int(round(duration * fs))
    s = 0.5 - 0.5 * np.cos(np.linspace(0.0, np.pi, n))
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    return quat.multiply(np.asarray(start, float), quat.from_rotvec(np.radians(angle_deg) * s[:, None] * axis))


def random_smooth_trajectory(fs: float, duration: float, max_rate: float = 2.0, seed: int = 0) -> np.ndarray:
    """Random smooth motion: body rates are low-pass filtered noise scaled to ``max_rate`` [rad/s]."""
    rng = np.random.default_rng(seed)
    n = int(round(duration * fs))
    knots = max(4, int(duration * 2))
    t_knots = np.linspace(0, n - 1, knots)
    rates = np.stack([np.interp(np.arange(n), t_knots, rng.uniform(-1, 1, knots)) for _ in range(3)], axis=1)
    rates *= max_rate
    dq = quat.from_rotvec(rates / fs)
    q = np.empty((n, 4))
    q[0] = quat.from_euler_zyx(rng.uniform(-np.pi, np.pi, 3) * [0.3, 0.3, 1.0])
    for k in range(1, n):
        q[k] = quat.multiply(q[k - 1], dq[k])
    return quat.normalize(q)


# ---------------------------------------------------------------------------------------------
# More trajectories and disturbances (each returns an array to pass to ``imu_from_orientation``)
# ---------------------------------------------------------------------------------------------

def gimbal_trajectory(fs: float, duration: float, amplitude_deg=(30.0, 20.0, 90.0), freq_hz=(0.11, 0.07, 0.05),
                      phase=(0.0, 0.5, 1.0)) -> np.ndarray:
    """Three-axis gimbal: roll, pitch, yaw [deg] each a sinusoid ``A sin(2π f t + φ)``; ``(n, 4)``."""
    t = np.arange(int(round(duration * fs))) / fs
    rpy = np.stack([np.radians(a) * np.sin(2 * np.pi * f * t + p) for a, f, p in zip(amplitude_deg, freq_hz, phase)], -1)
    return quat.from_euler_zyx(rpy)


def turntable_trajectory(fs: float, duration: float, rate_deg_s: float = 30.0, tilt_deg: float = 20.0,
                         tilt_axis=(1.0, 0.0, 0.0)) -> np.ndarray:
    """Turntable spinning about the vertical at ``rate_deg_s`` with the sensor mounted tilted by
    ``tilt_deg`` about the body ``tilt_axis``: ``q(t) = Rz(rate·t) ⊗ R(tilt)``; ``(n, 4)``."""
    n = int(round(duration * fs))
    yaw = np.radians(rate_deg_s) * np.arange(n) / fs
    qz = np.stack([np.cos(yaw / 2), np.zeros(n), np.zeros(n), np.sin(yaw / 2)], -1)
    axis = np.asarray(tilt_axis, float) / np.linalg.norm(tilt_axis)
    return quat.multiply(qz, quat.from_rotvec(np.radians(tilt_deg) * axis))


def random_walk_bias(n: int, fs: float, sigma: float = 1e-4, initial=(0.0, 0.0, 0.0), seed: int = 0) -> np.ndarray:
    """Gyro bias ``(n, 3)`` [rad/s]: ``initial`` plus a random walk of ``sigma`` [rad/s/√s]."""
    rng = np.random.default_rng(seed)
    steps = sigma * np.sqrt(1.0 / fs) * rng.standard_normal((n, 3))
    steps[0] = 0.0
    return np.asarray(initial, float) + np.cumsum(steps, axis=0)


def linear_acceleration_bursts(n: int, fs: float, bursts=((5.0, 1.0, (3.0, 0.0, 0.0)),)) -> np.ndarray:
    """Linear acceleration in ENU ``(n, 3)`` [m/s²]: each burst ``(start [s], duration [s], peak
    vector [m/s²])`` is a raised-cosine pulse (smooth, zero outside the burst)."""
    out = np.zeros((n, 3))
    t = np.arange(n) / fs
    for start, dur, peak in bursts:
        sel = (t >= start) & (t < start + dur)
        w = 0.5 - 0.5 * np.cos(2 * np.pi * (t[sel] - start) / dur)
        out[sel] += w[:, None] * np.asarray(peak, float)
    return out


def vibration(n: int, fs: float, amplitude: float = 1.0, freq_hz: float = 25.0, start: float = 0.0,
              stop: float | None = None, seed: int = 0) -> np.ndarray:
    """Vibration as linear acceleration in ENU ``(n, 3)`` [m/s²]: a sinusoid of ``freq_hz`` with a
    random direction per axis and random phases, amplitude ``amplitude`` per axis, between
    ``start`` and ``stop`` [s] (default: to the end)."""
    rng = np.random.default_rng(seed)
    t = np.arange(n) / fs
    ph = rng.uniform(0, 2 * np.pi, 3)
    out = amplitude * np.sin(2 * np.pi * freq_hz * t[:, None] + ph)
    active = (t >= start) & (t < (np.inf if stop is None else stop))
    return out * active[:, None]


def mag_disturbance_intervals(n: int, fs: float, intervals=((10.0, 20.0, (30.0, 0.0, 0.0)),)) -> np.ndarray:
    """Magnetic disturbance in ENU ``(n, 3)`` [µT]: a constant field vector added during each
    ``(start [s], stop [s], vector [µT])`` interval."""
    out = np.zeros((n, 3))
    t = np.arange(n) / fs
    for start, stop, vec in intervals:
        out[(t >= start) & (t < stop)] += np.asarray(vec, float)
    return out


# ---------------------------------------------------------------------------------------------
# Recordings shaped like BROAD's (rest, then movement; optical position; written in its layout)
# ---------------------------------------------------------------------------------------------

def rest_then_motion_trajectory(fs: float, rest_s: float, motion_s: float, max_rate: float = 2.0,
                                knots_per_s: float = 2.0, ramp_s: float = 0.5, start_rpy_deg=(0.0, 0.0, 0.0),
                                seed: int = 0) -> np.ndarray:
    """``rest_s`` seconds at the orientation ``start_rpy_deg`` (roll, pitch, yaw [deg]), then
    ``motion_s`` seconds of smooth random rotation; ``(n, 4)``, ``n = round((rest_s + motion_s)·fs)``.

    The body rates are piecewise-linear between random knots (``knots_per_s`` per second, each
    axis uniform in ``[-max_rate, max_rate]`` rad/s), faded in by a raised cosine over ``ramp_s``
    seconds after the rest (no jump in the rate), and integrated exactly (``from_rotvec``)."""
    rng = np.random.default_rng(seed)
    n = int(round((rest_s + motion_s) * fs))
    t = np.arange(n) / fs
    knots = max(4, int(round(motion_s * knots_per_s)) + 1)
    t_knots = rest_s + np.linspace(0.0, motion_s, knots)
    rates = np.stack([np.interp(t, t_knots, rng.uniform(-1.0, 1.0, knots)) for _ in range(3)], axis=1) * max_rate
    ramp = np.clip((t - rest_s) / ramp_s, 0.0, 1.0) if ramp_s > 0 else (t >= rest_s).astype(float)
    rates *= (0.5 - 0.5 * np.cos(np.pi * ramp))[:, None]
    dq = quat.from_rotvec(rates / fs)
    q = np.empty((n, 4))
    q[0] = quat.from_euler_zyx(np.radians(start_rpy_deg))
    for k in range(1, n):
        q[k] = quat.multiply(q[k - 1], dq[k])
    return quat.normalize(q)


def translation_moves(n: int, fs: float, moves=((5.0, 0.6, (0.3, 0.0, 0.0)),), start_pos=(0.0, 0.0, 0.0)):
    """Point-to-point translations in ENU: each move ``(start [s], duration T [s], displacement
    vector [m])`` follows the minimum-jerk profile ``d·(10s³ − 15s⁴ + 6s⁵)``, ``s = (t − start)/T``
    (rest before and after; peak acceleration ``5.77·|d|/T²``). Returns ``(pos (n, 3) [m],
    lin_acc_earth (n, 3) [m/s²])``: the position and its exact second derivative, so that an
    optical position (``opt_pos``) and the linear acceleration the IMU feels agree."""
    t = np.arange(n) / fs
    pos = np.tile(np.asarray(start_pos, float), (n, 1))
    acc = np.zeros((n, 3))
    for start, dur, disp in moves:
        d = np.asarray(disp, float)
        s = np.clip((t - start) / dur, 0.0, 1.0)
        inside = (t > start) & (t < start + dur)
        pos += (10 * s ** 3 - 15 * s ** 4 + 6 * s ** 5)[:, None] * d
        acc += np.where(inside, (60 * s - 180 * s ** 2 + 120 * s ** 3) / dur ** 2, 0.0)[:, None] * d
    return pos, acc


def taps(n: int, fs: float, times=(5.0,), peak: float = 8.0, freq_hz: float = 60.0, decay_s: float = 0.02,
         seed: int = 0) -> np.ndarray:
    """Taps (a finger knocking on the sensor) as linear acceleration in ENU ``(n, 3)`` [m/s²]: at
    each time [s] a sinusoid of ``freq_hz`` decaying with time constant ``decay_s``, of ``peak``
    m/s² along a random direction. Their displacement is micrometres: no optical system sees it."""
    rng = np.random.default_rng(seed)
    out = np.zeros((n, 3))
    t = np.arange(n) / fs
    for t0 in times:
        u = rng.standard_normal(3)
        u /= np.linalg.norm(u)
        tau = t - t0
        on = tau >= 0
        out[on] += (peak * np.exp(-tau[on] / decay_s) * np.sin(2 * np.pi * freq_hz * tau[on]))[:, None] * u
    return out
