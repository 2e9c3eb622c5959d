"""The one table of every filter the package runs, by CLI name (``CATALOG``).

Each row (``FilterEntry``) says what the filter is (``kind``), how tables and plots name it
(``label``), what it does in one line (``description``) and, for a classic filter, its class.
Everything that lists filters reads this table: ``togglecf.filters.FILTERS`` and ``make_filter``
(its classic rows), ``togglecf.registry`` (``FILTER_NAMES``, ``TRAINED``, ``CLASSIC_NAMES``), the
CLI's choices, the study report's labels and the docs' table of defaults.

Kinds: ``classic`` (a class of this package, built from its settings), ``trained`` (driven by a
``togglecf train`` model directory), ``pretrained`` (the model the package ships) and ``reference``
(the ``vqf`` package). The table sits in this ML-free package so that the classic view below needs
no import from above; the rows without a class are built by ``togglecf.registry.FilterSpec``.
"""
from __future__ import annotations

from dataclasses import dataclass
from types import MappingProxyType

from togglecf.filters.acc_mag import AccMagFilter
from togglecf.filters.aqua import AquaFilter
from togglecf.filters.complementary import ComplementaryFilter
from togglecf.filters.ekf import EKFFilter
from togglecf.filters.gyro_only import GyroOnlyFilter
from togglecf.filters.madgwick import MadgwickFilter
from togglecf.filters.mahony import MahonyFilter
from togglecf.filters.vqf_core import VQFCoreFilter

__all__ = ["FilterEntry", "CATALOG", "KINDS", "CLASSIC", "TRAINED_KIND", "PRETRAINED", "REFERENCE", "names_of"]

#: a filter class of this package, built from its settings dataclass
CLASSIC = "classic"
#: driven by the models and learned gains of a ``togglecf train`` model directory (``--models DIR``)
TRAINED_KIND = "trained"
#: the pretrained model the package ships (or a portable model file, ``--models FILE.npz``)
PRETRAINED = "pretrained"
#: the reference implementation, the ``vqf`` package at its defaults (the ``vqf`` extra)
REFERENCE = "reference"
#: every kind, in the order the table lists them
KINDS = (CLASSIC, TRAINED_KIND, PRETRAINED, REFERENCE)


@dataclass(frozen=True)
class FilterEntry:
    """One filter: ``name`` (its CLI name), ``kind`` (one of ``KINDS``), ``label`` (its short name in
    tables and figures), ``description`` (one line) and ``cls`` (the class of a classic filter, whose
    ``name`` is this name; None for the other kinds)."""

    name: str
    kind: str
    label: str
    description: str
    cls: type | None = None

    def __post_init__(self):
        if self.kind not in KINDS:
            raise ValueError(f"{self.name}: kind {self.kind!r} is none of {KINDS}")
        if (self.cls is not None) != (self.kind == CLASSIC):
            raise ValueError(f"{self.name}: a class is given for, and only for, a {CLASSIC} filter")
        if self.cls is not None and self.cls.name != self.name:
            raise ValueError(f"{self.name}: the class {self.cls.__name__} is named {self.cls.name!r}")


def _table(*entries: FilterEntry) -> MappingProxyType:
    table = {e.name: e for e in entries}
    if len(table) != len(entries):
        raise ValueError("a filter name is given twice")
    return MappingProxyType(table)


#: every filter by CLI name, in the order the CLI lists them (read-only)
CATALOG = _table(
    FilterEntry("accmag", CLASSIC, "acc/mag only", "orientation from each sample's accelerometer (and "
                "magnetometer) alone: no gyroscope, no memory", AccMagFilter),
    FilterEntry("aqua", CLASSIC, "AQUA", "AQUA (Valenti et al. 2015): algebraic quaternion complementary filter "
                "with adaptive gain and gyro-bias estimation", AquaFilter),
    FilterEntry("cf", CLASSIC, "fixed-gain CF", "quaternion complementary filter with one fixed time constant τ [s]",
                ComplementaryFilter),
    FilterEntry("ekf", CLASSIC, "error-state KF", "error-state Kalman filter in the style of MATLAB's "
                "imufilter/ahrsfilter", EKFFilter),
    FilterEntry("gyro", CLASSIC, "gyro only", "strapdown gyroscope integration, never corrected (the drift "
                "baseline)", GyroOnlyFilter),
    FilterEntry("madgwick", CLASSIC, "Madgwick", "Madgwick's gradient-descent filter (gain β [rad/s])",
                MadgwickFilter),
    FilterEntry("mahony", CLASSIC, "Mahony", "Mahony's PI filter (gains Kp, Ki)", MahonyFilter),
    FilterEntry("vqf_core", CLASSIC, "VQF core", "the VQF algorithm (Laidig & Seel 2023) written from the paper: "
                "rest and motion gyro-bias estimation, magnetic disturbance rejection", VQFCoreFilter),
    FilterEntry("toggling", TRAINED_KIND, "toggling CF", "complementary filter whose gains the models of a model "
                "directory switch per sample (--models DIR)"),
    FilterEntry("vqf_toggling", TRAINED_KIND, "VQF core + learned time constants", "the VQF core with the time "
                "constants the models of a model directory choose per sample (--models DIR)"),
    FilterEntry("learned_vqf", PRETRAINED, "learned VQF (pretrained)", "the pretrained learned VQF the package "
                "ships (--models FILE.npz: another portable model)"),
    FilterEntry("vqf", REFERENCE, "VQF", "the reference VQF: the vqf package (dlaidig/vqf) at its defaults, the "
                "vqf extra"),
)


def names_of(*kinds: str) -> tuple:
    """The names of the table's filters of ``kinds`` (all kinds if none given), in table order."""
    unknown = set(kinds) - set(KINDS)
    if unknown:
        raise ValueError(f"unknown kind(s) {sorted(unknown)}; known: {KINDS}")
    return tuple(n for n, e in CATALOG.items() if not kinds or e.kind in kinds)
