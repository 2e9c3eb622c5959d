"""Units at the boundary: the factors that turn a sensor's units into the package's (rad/s, m/s², µT, s).

One table per quantity, unit name -> factor to SI, shared by the live stream (``togglecf stream
--units``) and the recording importer (``togglecf import --units``). ``g`` is standard gravity
(9.80665 m/s², what an accelerometer's data sheet means by g), not the 9.81 m/s² BROAD's
accelerometers read at rest (``togglecf.data.broad.GRAVITY``).

``unit_mismatch`` is the one plausibility check of a sensor's units, shared by the trial loader
(``togglecf.data.broad``) and the live stream's first seconds: it refuses only what another unit
explains, never vigorous motion.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

__all__ = ["STANDARD_GRAVITY", "GYR_UNITS", "ACC_UNITS", "MAG_UNITS", "TIME_UNITS", "UNIT_TABLES", "parse_units",
           "PLAUSIBLE", "SI_NAMES", "UnitMismatch", "unit_mismatch", "units_option"]

STANDARD_GRAVITY = 9.80665  # m/s²
#: unit name -> factor to rad/s
GYR_UNITS = {"rad/s": 1.0, "rads": 1.0, "dps": math.pi / 180.0, "deg/s": math.pi / 180.0}
#: unit name -> factor to m/s²
ACC_UNITS = {"m/s2": 1.0, "ms2": 1.0, "g": STANDARD_GRAVITY, "mg": STANDARD_GRAVITY / 1000.0}
#: unit name -> factor to µT (1 gauss = 100 µT)
MAG_UNITS = {"uT": 1.0, "ut": 1.0, "nT": 1e-3, "nt": 1e-3, "mT": 1000.0, "G": 100.0, "gauss": 100.0, "mG": 0.1,
             "mg": 0.1}
#: unit name -> factor to s
TIME_UNITS = {"s": 1.0, "ms": 1e-3, "us": 1e-6}
#: quantity -> its table, in the order ``parse_units`` returns the factors
UNIT_TABLES = {"gyr": GYR_UNITS, "acc": ACC_UNITS, "mag": MAG_UNITS}


def parse_units(spec: str | None, option: str = "--units") -> tuple[float, float, float]:
    """``"gyr=dps,acc=g,mag=uT"`` (any subset; the rest rad/s, m/s², µT) -> SI factors (gyr, acc, mag).
    A ``ValueError`` names ``option``, the quantity and the unit for an unknown one."""
    chosen = {"gyr": "rad/s", "acc": "m/s2", "mag": "uT"}
    for item in (spec or "").split(","):
        if not item.strip():
            continue
        key, _, val = item.partition("=")
        key, val = key.strip(), val.strip()
        if key not in UNIT_TABLES:
            raise ValueError(f"{option}: unknown quantity {key!r} (gyr, acc, mag)")
        if val not in UNIT_TABLES[key]:
            raise ValueError(f"{option}: unknown unit {val!r} for {key} (one of {', '.join(UNIT_TABLES[key])})")
        chosen[key] = val
    return tuple(UNIT_TABLES[k][chosen[k]] for k in ("gyr", "acc", "mag"))


#: quantity -> (statistic of the samples' norms, its plausible range in the package's unit, the other units
#: a reading may be in). acc: the median |acc| holds gravity (9.81 m/s² at rest; a phone in a running hand
#: reads 20-24 m/s²); gyr: the 99th percentile |gyr| stays within the top of common gyro ranges (±2000 °/s
#: = 34.9 rad/s: a gyro in °/s exceeds it as soon as it turns faster than 35 °/s); mag: the median |mag|
#: is the earth's field, 25-65 µT, disturbed indoors
PLAUSIBLE = {
    "acc": ("median", 4.5, 100.0, ("g", "mg")),
    "gyr": ("p99", 0.0, 35.0, ("dps",)),
    "mag": ("median", 10.0, 150.0, ("gauss", "mT", "nT")),
}
#: the package's unit of each quantity, as printed
SI_NAMES = {"gyr": "rad/s", "acc": "m/s²", "mag": "µT"}
_SHOWN = {"dps": "°/s"}
_STATISTIC_NAMES = {"median": "median", "p99": "99th percentile"}


@dataclass(frozen=True)
class UnitMismatch:
    """Samples of ``quantity`` whose ``statistic`` of the norms (``value``, in the unit they were read as) is
    implausible in that unit and plausible in ``unit`` (a key of ``UNIT_TABLES[quantity]``)."""

    quantity: str
    statistic: str
    value: float
    unit: str

    def describe(self) -> str:
        """``"median |acc| = 1: looks like g, expected m/s²"``."""
        return (f"{_STATISTIC_NAMES[self.statistic]} |{self.quantity}| = {self.value:.3g}: looks like "
                f"{_SHOWN.get(self.unit, self.unit)}, expected {SI_NAMES[self.quantity]}")


def unit_mismatch(quantity: str, samples, factor: float = 1.0) -> UnitMismatch | None:
    """The unit ``samples (N, 3)`` (converted to the package's unit with ``factor``, the factor of the unit
    they were read in) look like when their statistic (``PLAUSIBLE``) is implausible as read and plausible
    in another unit; ``None`` when plausible, when no other unit explains it, or without a finite sample."""
    statistic, low, high, others = PLAUSIBLE[quantity]
    norms = np.linalg.norm(np.asarray(samples, dtype=float), axis=1)
    norms = norms[np.isfinite(norms)]
    if norms.size == 0:
        return None
    value = float(np.median(norms) if statistic == "median" else np.percentile(norms, 99))
    if low <= value <= high:
        return None
    as_read = value / factor
    for unit in others:
        if low <= as_read * UNIT_TABLES[quantity][unit] <= high:
            return UnitMismatch(quantity, statistic, value, unit)
    return None


def units_option(spec: str | None, quantity: str, unit: str) -> str:
    """``--units`` of ``spec`` with ``quantity`` read in ``unit``, in place or appended:
    ``units_option("gyr=dps,acc=m/s2", "acc", "g")`` -> ``"gyr=dps,acc=g"``."""
    items = [i.strip() for i in (spec or "").split(",") if i.strip()]
    given = [k for k, i in enumerate(items) if i.partition("=")[0].strip() == quantity]
    if given:
        items[given[0]] = f"{quantity}={unit}"
        return ",".join(items)
    return ",".join(items + [f"{quantity}={unit}"])
