"""Gyroscope-only strapdown integration (the drift baseline).

Per sample: ``q = q ⊗ exp(ω Δt / 2)`` (exact integration for a rate constant over Δt).
The orientation is initialised once from the first valid acc(/mag) sample (heading 0 in
6D); afterwards acc and mag are never used, so the error grows with the gyro bias.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

from numba import njit

from togglecf.filters.base import (
    FilterSettings,
    OrientationFilter,
    initialize_from_sample,
    load_quat,
    propagate_gyro,
    store_quat,
    vector_ok,
)

__all__ = ["GyroOnlyFilter", "GyroSettings"]


@dataclass(frozen=True)
class GyroSettings(FilterSettings):
    """No parameters besides ``max_dt`` (see ``FilterSettings``)."""


class GyroCoefficients(NamedTuple):
    """``params`` of ``gyro_step``: only the common ``use_mag``, ``max_dt`` (see ``filters.base``)."""

    use_mag: float
    max_dt: float


@njit(cache=True)
def gyro_step(state, params, gyr, acc, mag, dt, diag):
    """One sample. diag: [1.0 if the gyro sample was integrated]."""
    use_mag, max_dt = params.use_mag > 0.5, params.max_dt
    diag[0] = 0.0
    if state[4] < 0.5:
        initialize_from_sample(state, acc, mag, use_mag and vector_ok(mag))
        return
    q, done = propagate_gyro(load_quat(state), gyr, dt, max_dt)  # q ⊗ exp(ω Δt / 2)
    diag[0] = 1.0 if done else 0.0
    store_quat(state, q)


class GyroOnlyFilter(OrientationFilter):
    """Strapdown gyro integration: ``GyroOnlyFilter(fs)``."""

    name = "gyro"
    Settings = GyroSettings
    Coefficients = GyroCoefficients
    diagnostic_names = ("gyro_integrated",)
    step = gyro_step

    def _coefficients(self) -> dict:
        return {}
