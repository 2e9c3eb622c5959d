"""Every filter the commands run, by name, and how to build one.

The names come from one table, ``CATALOG`` (``togglecf.filters.catalog``: name -> ``FilterEntry``
with kind, label, one-line description and, for a classic filter, its class); ``FILTER_NAMES``,
``CLASSIC_NAMES`` and ``TRAINED`` are views of it, and so are the CLI's choices, the study report's
labels and the docs' table of defaults.

A ``FilterSpec`` names a filter and everything needed to build it at any rate: the settings
overrides of a classic filter, or the model directory of the trained toggling filter (its
gains come from the directory). Specs validate on construction, without a sampling rate:
a classic filter's settings dataclass checks its values, a toggling spec checks that the model
directory holds models and the gains of its mode. ``vqf`` is the reference implementation (the ``vqf``
package, dlaidig/vqf: an optional dependency, the ``vqf`` extra) at its defaults, imported when a spec of it
is built, never by this module.
"""
from __future__ import annotations

from dataclasses import dataclass, field, fields
from importlib.metadata import version
from pathlib import Path

import numpy as np

from togglecf.core.extras import check_extra, deferred
from togglecf.core.io import file_sha256
from togglecf.filters import FILTERS, FilterOutput, OrientationFilter
from togglecf.filters.catalog import CATALOG, CLASSIC, TRAINED_KIND, FilterEntry, names_of
from togglecf.toggling.gains import load_gains
from togglecf.toggling.load import load_toggling_filter, model_dir_digest
from togglecf.toggling.pretrained import PRETRAINED_FILE, LearnedVQF, load_pretrained, pretrained_settings

__all__ = ["CATALOG", "FilterEntry", "FilterSpec", "TOGGLING", "VQF_TOGGLING", "LEARNED_VQF", "REFERENCE_VQF",
           "TRAINED", "CLASSIC_NAMES", "FILTER_NAMES", "filter_spec", "is_portable_file", "ReferenceVQF",
           "ReferenceVQFSettings"]

#: every name a command accepts, in the table's order (``CATALOG``)
FILTER_NAMES = names_of()
#: the classic filters (a class of ``togglecf.filters`` each): the ones ``tune`` searches
CLASSIC_NAMES = names_of(CLASSIC)
#: the filters trained by ``togglecf train`` (models + learned gains in a model directory)
TRAINED = names_of(TRAINED_KIND)
#: CLI name of the trained toggling filter (``--filter toggling --models DIR``)
TOGGLING = CATALOG["toggling"].name
#: CLI name of the VQF core with learned time constants (``--filter vqf_toggling --models DIR``)
VQF_TOGGLING = CATALOG["vqf_toggling"].name
#: CLI name of the pretrained learned VQF the package ships (``togglecf.LearnedVQF``; no --models needed, or
#: ``--models FILE.npz``: another portable model, e.g. from ``togglecf train --from-pretrained``)
LEARNED_VQF = CATALOG["learned_vqf"].name
#: CLI name of the reference VQF (the ``vqf`` package at its defaults; the ``vqf`` extra)
REFERENCE_VQF = CATALOG["vqf"].name

#: what needs the ``vqf`` extra, in its one-line message
_VQF_WHAT = f"the {REFERENCE_VQF} filter (the reference VQF, dlaidig/vqf)"
vqf_package = deferred("vqf", extra="vqf", what=_VQF_WHAT)
#: largest relative deviation of a Δt from 1/fs the fixed-rate reference accepts in ``update_batch``
_FIXED_RATE_TOLERANCE = 0.1


@dataclass(frozen=True)
class ReferenceVQFSettings:
    """The reference VQF's settings: the ``vqf`` package's defaults (``params``: its names, its units)."""

    package_version: str
    params: dict

    def __str__(self):
        return (f"vqf {self.package_version} at its defaults (tauAcc {self.params['tauAcc']:g} s, "
                f"tauMag {self.params['tauMag']:g} s)")


class ReferenceVQF:
    """The ``vqf`` package's ``VQF(1/fs)`` behind the interface of togglecf's filters (``update``,
    ``update_batch`` -> ``FilterOutput``), as the study runs it (``updateBatch``). It runs at the fixed
    sampling time ``1/fs``: ``update`` ignores ``dt`` (a stream's jitter), ``update_batch`` refuses a ``dt``
    that is not ``1/fs`` (an irregular log)."""

    def __init__(self, fs: float, use_mag: bool = True):
        self.fs, self.use_mag = float(fs), bool(use_mag)
        self._vqf = vqf_package.VQF(1.0 / self.fs)
        self._quat_key = "quat9D" if self.use_mag else "quat6D"

    def update(self, gyr, acc, mag=None, dt=None) -> np.ndarray:
        """One sample; the orientation after it ``[w, x, y, z]`` (sensor -> ENU)."""
        gyr, acc = np.ascontiguousarray(gyr, dtype=float), np.ascontiguousarray(acc, dtype=float)
        if self.use_mag:
            self._vqf.update(gyr, acc, np.ascontiguousarray(mag, dtype=float))
            return np.asarray(self._vqf.getQuat9D())
        self._vqf.update(gyr, acc)
        return np.asarray(self._vqf.getQuat6D())

    def update_batch(self, gyr, acc, mag=None, dt=None) -> FilterOutput:
        """``(N, 3)`` arrays -> ``FilterOutput`` (``quat (N, 4)``; diagnostics ``rest``, 9D also ``mag_disturbed``)."""
        self._check_fixed_rate(dt)
        out = self._vqf.updateBatch(np.ascontiguousarray(gyr, dtype=float), np.ascontiguousarray(acc, dtype=float),
                                    np.ascontiguousarray(mag, dtype=float) if self.use_mag else None)
        diagnostics = {"rest": np.asarray(out["restDetected"], float)}
        if self.use_mag:
            diagnostics["mag_disturbed"] = np.asarray(out["magDistDetected"], float)
        return FilterOutput(np.asarray(out[self._quat_key]), diagnostics)

    def _check_fixed_rate(self, dt) -> None:
        if dt is None:
            return
        dt = np.asarray(dt, dtype=float)
        dt = dt[np.isfinite(dt)]
        if dt.size and np.max(np.abs(dt * self.fs - 1.0)) > _FIXED_RATE_TOLERANCE:
            raise ValueError(f"the {REFERENCE_VQF} filter runs at the fixed sampling time 1/fs ({1e3 / self.fs:.4g} "
                             f"ms); these time stamps are {1e3 * dt.min():.4g} to {1e3 * dt.max():.4g} ms apart")


@dataclass(frozen=True)
class FilterSpec:
    """What to build: ``name`` (one of ``FILTER_NAMES``), ``params`` (settings overrides of a
    classic filter, physical units as in its ``Settings``), ``models`` (model directory of the
    trained filters; for ``learned_vqf`` a portable model file, None: the shipped one), ``use_mag`` (9D, else 6D)."""

    name: str
    params: dict = field(default_factory=dict)
    models: str | None = None
    use_mag: bool = True

    def __post_init__(self):
        object.__setattr__(self, "params", dict(self.params))
        if self.name == REFERENCE_VQF:
            if self.params or self.models is not None:
                raise ValueError(f"the {REFERENCE_VQF} filter is the reference VQF at its defaults: it takes no "
                                 "--param and no --models")
            check_extra("vqf", what=_VQF_WHAT)  # not installed: one line naming the extra
            return
        if self.name == LEARNED_VQF:
            if self.params:
                raise ValueError(f"the {LEARNED_VQF} filter is the pretrained model the package ships: it takes no "
                                 "--param")
            if self.models is not None:  # a portable model file instead of the shipped one
                if not is_portable_file(self.models):
                    raise ValueError(f"--filter {LEARNED_VQF} --models takes a portable model file (.npz, from "
                                     f"`togglecf train --from-pretrained`), not {self.models} (a model directory runs "
                                     f"with --filter {VQF_TOGGLING})")
                object.__setattr__(self, "models", str(Path(self.models).resolve()))
            pretrained_settings(self.use_mag, self.models)  # none shipped, a bad file, no settings of this mode: refused
            return
        if self.name in TRAINED:
            if self.params:
                raise ValueError(f"the {self.name} filter takes no --param: its models and learned gains come from "
                                 "--models DIR")
            if not self.models:
                raise ValueError(f"the {self.name} filter needs a model directory (--models DIR, a `togglecf train` "
                                 "output)")
            object.__setattr__(self, "models", str(Path(self.models).resolve()))
            load_gains(self.models, use_mag=self.use_mag, kind=self.name)  # no models or no gains of this mode: refused
            return
        if self.name not in FILTERS:
            raise ValueError(f"unknown filter {self.name!r}; available: {', '.join(FILTER_NAMES)}")
        if self.models is not None:
            raise ValueError(f"--models is for --filter {'/'.join(TRAINED)}, not {self.name}")
        cls = FILTERS[self.name]
        known = {f.name for f in fields(cls.Settings)}
        unknown = sorted(set(self.params) - known)
        if unknown:
            raise ValueError(f"{self.name}: unknown setting(s) {unknown}; known: {sorted(known)}")
        cls.Settings(**self.params)  # the settings' own checks (finite, ranges), no rate needed

    @property
    def settings(self):
        """The settings the filter runs with (the learned gains for the toggling filter)."""
        if self.name == REFERENCE_VQF:
            return ReferenceVQFSettings(version("vqf"), dict(vqf_package.VQF(0.01).params))
        if self.name == LEARNED_VQF:
            return pretrained_settings(self.use_mag, self.models)
        if self.name in TRAINED:
            return load_gains(self.models, use_mag=self.use_mag, kind=self.name)
        return FILTERS[self.name].Settings(**self.params)

    def build(self, fs: float) -> OrientationFilter | ReferenceVQF:
        """The filter at sampling rate ``fs`` [Hz], freshly initialised."""
        if self.name == REFERENCE_VQF:
            return ReferenceVQF(fs, use_mag=self.use_mag)
        if self.name == LEARNED_VQF:
            return LearnedVQF(fs, use_mag=self.use_mag, model=self.models)
        if self.name in TRAINED:
            return load_toggling_filter(self.models, fs, use_mag=self.use_mag, kind=self.name)
        return FILTERS[self.name](fs, use_mag=self.use_mag, **self.params)

    def identity(self):
        """What results computed with this spec depend on beyond name and params (journal keys):
        the content of the model directory for the toggling filter, of the shipped model file for the
        pretrained one, of the package's version for the reference VQF."""
        if self.name == REFERENCE_VQF:
            return f"vqf {version('vqf')}"
        if self.name == LEARNED_VQF:
            return file_sha256(self.models or PRETRAINED_FILE)
        return model_dir_digest(self.models) if self.name in TRAINED else None

    def as_params(self) -> dict:
        """The parameter dict of sweeps and journals (``{"models": DIR}`` for the toggling filter)."""
        if self.name == LEARNED_VQF:
            return {"models": self.models} if self.models else {}
        return {"models": self.models} if self.name in TRAINED else dict(self.params)


def is_portable_file(path) -> bool:
    """``path`` names a portable model file (``learn.portable``: ``.npz``), not a model directory."""
    return str(path).lower().endswith(".npz")


def filter_spec(name: str, params: dict | None = None, use_mag: bool = True) -> FilterSpec:
    """A spec from a sweep's parameter dict: ``{"models": DIR}`` for the toggling filter, settings
    overrides for the others."""
    params = dict(params or {})
    if name in TRAINED or name == LEARNED_VQF:
        models = params.pop("models", None)
        return FilterSpec(name, params, models=models, use_mag=use_mag)
    return FilterSpec(name, params, use_mag=use_mag)
