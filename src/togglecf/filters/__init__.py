"""Orientation filters, one module per algorithm; ``FILTERS`` maps the CLI names of the classic
filters to their classes: the ``classic`` rows of ``catalog.CATALOG``, the one table of every filter.

All filters output sensor -> ENU quaternions ``[w, x, y, z]``; ``FilterOutput.in_frame``
converts to NED or NWU.
"""
from togglecf.filters.acc_mag import AccMagFilter, AccMagSettings
from togglecf.filters.aqua import AquaFilter, AquaSettings
from togglecf.filters.base import FilterOutput, FilterSettings, OrientationFilter, dt_from_timestamps
from togglecf.filters.catalog import CATALOG, CLASSIC
from togglecf.filters.complementary import CFSettings, ComplementaryFilter
from togglecf.filters.ekf import EKFFilter, EKFSettings
from togglecf.filters.gyro_only import GyroOnlyFilter, GyroSettings
from togglecf.filters.madgwick import MadgwickFilter, MadgwickSettings
from togglecf.filters.mahony import MahonyFilter, MahonySettings
from togglecf.filters.vqf_core import VQFCoreFilter, VQFCoreSettings

#: classic filter name -> class, in the table's order (a view of ``catalog.CATALOG``)
FILTERS = {name: entry.cls for name, entry in CATALOG.items() if entry.kind == CLASSIC}


def make_filter(name: str, fs: float, use_mag: bool = True, **settings) -> OrientationFilter:
    """Construct a classic filter by its CLI name at ``fs`` [Hz] with settings overrides (physical units as
    in its ``Settings``), e.g. ``make_filter('cf', 285.7, tau=2.0)``."""
    try:
        cls = FILTERS[name]
    except KeyError:
        raise ValueError(f"unknown filter {name!r}; available: {', '.join(sorted(FILTERS))}") from None
    return cls(fs, use_mag=use_mag, **settings)


__all__ = ["FILTERS", "make_filter", "OrientationFilter", "FilterOutput", "FilterSettings", "dt_from_timestamps",
           "ComplementaryFilter", "CFSettings", "GyroOnlyFilter", "GyroSettings", "AccMagFilter", "AccMagSettings",
           "MadgwickFilter", "MadgwickSettings", "MahonyFilter", "MahonySettings", "AquaFilter", "AquaSettings",
           "EKFFilter", "EKFSettings", "VQFCoreFilter", "VQFCoreSettings"]
