"""Time constants of the filters' first-order corrections and their per-sample gains.

Every gain of the complementary filters (the fixed CF, AQUA, the toggling CF, their gyro-bias
low-passes) is a time constant τ [s] in the settings, the same at any sampling rate. Each filter
converts it once, from its *nominal* sampling time ``Ts = 1/fs``, into the per-sample gain its
kernel uses (its ``Coefficients``):

    k = 1 − exp(−Ts/τ)          (``gain_from_tau``, VQF's convention)

τ = 0 gives k = 1 (the measurement replaces the estimate every sample); τ < 0 gives k = 0 (the
update is off; VQF's convention too). Like VQF, the coefficients use the nominal ``Ts``, not each
sample's Δt (the gyro is still integrated over the actual Δt): a jittery or gappy Δt changes the
correction's time constant in proportion to the local rate error only.

``tau_from_gain`` (τ = −Ts/ln(1 − α)) gives the time constant of a per-sample gain α at a rate;
the filters' defaults are such time constants, rounded to 4 significant digits, of gains tuned at
BROAD's rate (285.714 Hz).
"""
from __future__ import annotations

import math

from numba import njit

__all__ = ["BROAD_FS", "gain", "gain_from_tau", "tau_from_gain"]

#: Hz, the rate of BROAD's IMU, at which the per-sample gains behind the defaults were tuned
BROAD_FS = 285.714


@njit(cache=True)
def gain_from_tau(tau: float, ts: float) -> float:
    """Per-sample gain of a first-order low-pass with time constant ``tau`` [s] at sampling time
    ``ts`` [s]: 1 − exp(−ts/τ) (1 for τ = 0). Compiled: the learned VQF's kernel calls it per sample."""
    return 1.0 if tau == 0.0 else 1.0 - math.exp(-ts / tau)


def gain(tau: float, ts: float) -> float:
    """Per-sample gain of time constant ``tau`` [s] at sampling time ``ts`` [s]: 1 − exp(−ts/τ),
    1 for τ = 0, 0 for τ < 0 (off)."""
    if not ts > 0:
        raise ValueError(f"sampling time must be > 0 s, got {ts}")
    return 0.0 if tau < 0.0 else gain_from_tau(float(tau), float(ts))


def tau_from_gain(alpha: float, ts: float = 1.0 / BROAD_FS) -> float:
    """The time constant [s] whose per-sample gain at ``ts`` is ``alpha``: −ts/ln(1 − α)
    (0 for α = 1, −1 (off) for α = 0)."""
    if not 0.0 <= alpha <= 1.0:
        raise ValueError(f"a per-sample gain is in [0, 1], got {alpha}")
    if alpha == 0.0:
        return -1.0
    if alpha == 1.0:
        return 0.0
    return -ts / math.log1p(-alpha)
