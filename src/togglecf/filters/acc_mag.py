"""Acc/mag-only orientation, recomputed from every sample (no gyroscope, no memory).

9D: ``q = from_acc_mag(a, m)`` (up = a/|a|, east = m × up, north = up × east).
6D: tilt from the accelerometer, heading held: the previous estimate's north direction
is used in place of the magnetometer (``acc_mag_quaternion``), so the heading stays where
the first sample put it (0) except for the coupling through tilt changes.
A sample whose acc (or, in 9D, mag) is invalid keeps the previous orientation.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

from numba import njit

from togglecf.filters.base import (
    FilterSettings,
    OrientationFilter,
    acc_mag_quaternion,
    initialize_from_sample,
    load_quat,
    store_quat,
    vector_ok,
)

__all__ = ["AccMagFilter", "AccMagSettings"]


@dataclass(frozen=True)
class AccMagSettings(FilterSettings):
    """No parameters besides ``max_dt`` (unused here; see ``FilterSettings``)."""


class AccMagCoefficients(NamedTuple):
    """``params`` of ``accmag_step``: only the common ``use_mag``, ``max_dt`` (see
    ``filters.base``; ``max_dt`` is unused, there is no gyro propagation)."""

    use_mag: float
    max_dt: float


@njit(cache=True)
def accmag_step(state, params, gyr, acc, mag, dt, diag):
    """One sample. diag: [1.0 if the orientation was measured, 1.0 if mag was used]."""
    use_mag = params.use_mag > 0.5
    mag_ok = use_mag and vector_ok(mag)
    diag[0] = 0.0
    diag[1] = 0.0
    if state[4] < 0.5:
        initialize_from_sample(state, acc, mag, mag_ok)
        return
    if not vector_ok(acc) or (use_mag and not mag_ok):
        return  # invalid measurement: hold the previous orientation
    ok, q = acc_mag_quaternion(load_quat(state), acc, mag, mag_ok)
    if ok:
        store_quat(state, q)
        diag[0] = 1.0
        diag[1] = 1.0 if mag_ok else 0.0


class AccMagFilter(OrientationFilter):
    """Per-sample acc/mag orientation: ``AccMagFilter(fs, use_mag=True)``."""

    name = "accmag"
    Settings = AccMagSettings
    Coefficients = AccMagCoefficients
    diagnostic_names = ("measured", "mag_used")
    step = accmag_step

    def _coefficients(self) -> dict:
        return {}
