"""One registry of every filter the commands run, the trained toggling filter included.

A ``FilterSpec`` names a filter and everything needed to build it at any rate: the settings
overrides of a classic filter, or the model directory of the trained toggling filter (its
gains come from the directory). Specs validate on construction, without a sampling rate:
a classic filter's settings dataclass checks its values, a toggling spec checks that the model
directory holds models and the gains of its mode.
"""
from __future__ import annotations

from dataclasses import dataclass, field, fields
from pathlib import Path

from togglecf.core.io import file_sha256
from togglecf.filters import FILTERS, OrientationFilter
from togglecf.toggling.gains import load_gains
from togglecf.toggling.load import load_toggling_filter, model_dir_digest
from togglecf.toggling.pretrained import PRETRAINED_FILE, LearnedVQF, load_pretrained, pretrained_settings

__all__ = ["FilterSpec", "TOGGLING", "VQF_TOGGLING", "LEARNED_VQF", "TRAINED", "FILTER_NAMES", "filter_spec"]

#: CLI name of the trained toggling filter (``--filter toggling --models DIR``)
TOGGLING = "toggling"
#: CLI name of the VQF core with learned time constants (``--filter vqf_toggling --models DIR``)
VQF_TOGGLING = "vqf_toggling"
#: CLI name of the pretrained learned VQF the package ships (``togglecf.LearnedVQF``; no --models needed)
LEARNED_VQF = "learned_vqf"
#: the filters trained by ``togglecf train`` (models + learned gains in a model directory)
TRAINED = (TOGGLING, VQF_TOGGLING)
#: every name a command accepts
FILTER_NAMES = tuple(sorted(FILTERS)) + TRAINED + (LEARNED_VQF,)


@dataclass(frozen=True)
class FilterSpec:
    """What to build: ``name`` (one of ``FILTER_NAMES``), ``params`` (settings overrides of a
    classic filter, physical units as in its ``Settings``), ``models`` (model directory of the
    toggling filter), ``use_mag`` (9D, else 6D)."""

    name: str
    params: dict = field(default_factory=dict)
    models: str | None = None
    use_mag: bool = True

    def __post_init__(self):
        object.__setattr__(self, "params", dict(self.params))
        if self.name == LEARNED_VQF:
            if self.params or self.models is not None:
                raise ValueError(f"the {LEARNED_VQF} filter is the pretrained model the package ships: it takes no "
                                 f"--param and no --models (a model directory runs with --filter {VQF_TOGGLING})")
            load_pretrained()  # none shipped: refused with what to do
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
        if self.name == LEARNED_VQF:
            return pretrained_settings(self.use_mag)
        if self.name in TRAINED:
            return load_gains(self.models, use_mag=self.use_mag, kind=self.name)
        return FILTERS[self.name].Settings(**self.params)

    def build(self, fs: float) -> OrientationFilter:
        """The filter at sampling rate ``fs`` [Hz], freshly initialised."""
        if self.name == LEARNED_VQF:
            return LearnedVQF(fs, use_mag=self.use_mag)
        if self.name in TRAINED:
            return load_toggling_filter(self.models, fs, use_mag=self.use_mag, kind=self.name)
        return FILTERS[self.name](fs, use_mag=self.use_mag, **self.params)

    def identity(self):
        """What results computed with this spec depend on beyond name and params (journal keys):
        the content of the model directory for the toggling filter, of the shipped model file for the
        pretrained one."""
        if self.name == LEARNED_VQF:
            return file_sha256(PRETRAINED_FILE)
        return model_dir_digest(self.models) if self.name in TRAINED else None

    def as_params(self) -> dict:
        """The parameter dict of sweeps and journals (``{"models": DIR}`` for the toggling filter)."""
        return {"models": self.models} if self.name in TRAINED else dict(self.params)


def filter_spec(name: str, params: dict | None = None, use_mag: bool = True) -> FilterSpec:
    """A spec from a sweep's parameter dict: ``{"models": DIR}`` for the toggling filter, settings
    overrides for the others."""
    params = dict(params or {})
    if name in TRAINED:
        models = params.pop("models", None)
        return FilterSpec(name, params, models=models, use_mag=use_mag)
    return FilterSpec(name, params, use_mag=use_mag)
