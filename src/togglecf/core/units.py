"""Units at the boundary: the factors that turn a sensor's units into the package's (rad/s, m/s², µT, s).

One table per quantity, unit name -> factor to SI, shared by the live stream (``togglecf stream
--units``) and the recording importer (``togglecf import --units``). ``g`` is standard gravity
(9.80665 m/s², what an accelerometer's data sheet means by g), not the 9.81 m/s² BROAD's
accelerometers read at rest (``togglecf.data.broad.GRAVITY``).
"""
from __future__ import annotations

import math

__all__ = ["STANDARD_GRAVITY", "GYR_UNITS", "ACC_UNITS", "MAG_UNITS", "TIME_UNITS", "UNIT_TABLES", "parse_units"]

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
