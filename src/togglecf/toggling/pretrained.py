"""The pretrained learned VQF the package ships: ``LearnedVQF(rate)`` runs it with no training, in the
style of ``vqf.VQF(Ts)``::

    import togglecf
    f = togglecf.LearnedVQF(100.0)                       # rate [Hz]; use_mag=False: 6D
    quat = f.update_batch(gyr, acc, mag).quat             # (N, 4) [w, x, y, z], sensor -> ENU

Where the model's settings of a mode change nothing (``VQFTogglingSettings.learning_off``), the
filter runs the VQF core alone, at the core's cost (``LearnedVQF.runs_core_alone``).

The model (``pretrained/learned_vqf.npz``: the compiled forest, the feature settings and ranges, and
the learned 9D and 6D settings; ``learn.portable``) and its model card (``pretrained/MODEL_CARD.md``:
data, rates, sensors, held-out numbers, limits, licences) are made by ``make run`` (step 5:
``pipelines/main.py``) and copied into the package by ``pipelines/ship_pretrained.py`` only when
the recipe passes the no-harm check on every dataset left out. Reading it needs numpy alone.
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from togglecf.filters.base import FilterOutput
from togglecf.filters.vqf_core import VQFCoreFilter
from togglecf.filters.vqf_toggling import VQFTogglingFilter, VQFTogglingSettings
from togglecf.learn.portable import PortableModel, load_portable, save_portable
from togglecf.toggling.gains import GAINS_FILE, MODES, load_gains, mode_name, settings_from_dict
from togglecf.toggling.inloop import ModelVQFTogglingFilter
from togglecf.toggling.load import load_compiled_models

__all__ = ["LearnedVQF", "PRETRAINED_DIR", "PRETRAINED_FILE", "MODEL_CARD_FILE", "VQF_MODES", "load_pretrained",
           "pretrained_settings", "portable_from_model_dir"]

#: where the package keeps the pretrained model and its card
PRETRAINED_DIR = Path(__file__).resolve().parent / "pretrained"
PRETRAINED_FILE = PRETRAINED_DIR / "learned_vqf.npz"
MODEL_CARD_FILE = PRETRAINED_DIR / "MODEL_CARD.md"
#: the gains.json modes a portable learned VQF carries
VQF_MODES = (mode_name("vqf_toggling", True), mode_name("vqf_toggling", False))
_LOADED: dict = {}


def load_pretrained(path=None) -> PortableModel:
    """The portable model at ``path`` (default: the one the package ships), read once per process."""
    path = Path(path) if path is not None else PRETRAINED_FILE
    if path == PRETRAINED_FILE and not path.is_file():
        raise FileNotFoundError(f"{path}: this installation ships no pretrained model (a source checkout before "
                                "`make run` and `python pipelines/ship_pretrained.py`); train one with `togglecf train`")
    key = str(path.resolve())
    if key not in _LOADED:
        _LOADED[key] = load_portable(path)
    return _LOADED[key]


class LearnedVQF:
    """The pretrained learned VQF at ``rate`` [Hz] (9D, or 6D with ``use_mag=False``): the VQF core with the
    shipped models in its loop (``filters.vqf_toggling``: per-state time constants, a heading back-off on the
    predicted magnetic disturbance; the model card says which the shipped settings use). ``update(gyr, acc, mag)``
    returns the orientation ``(4,)``; ``update_batch`` returns a ``FilterOutput`` with ``.quat (N, 4)``
    and the diagnostics; ``get_state`` / ``set_state`` save and restore everything the running filter
    holds. Units: gyr rad/s, acc m/s², mag µT. ``model``: another portable file (``learn.portable``)
    instead of the shipped one.

    It holds one of two filters, ``runner``:

    - learning off in this mode (``VQFTogglingSettings.learning_off``: every learned value equals the
      core's): the VQF core alone (``VQFCoreFilter`` with ``settings.core_settings``), no feature
      window, no trees; ``runs_core_alone`` is True. The same orientation as the models in the loop
      within rounding (the learned path rebuilds the core's coefficients from exp(ln τ)). Diagnostics:
      the core's (``VQFCoreFilter.diagnostic_names``), no predictions and no ``fallback``; the state is
      the core's.
    - else the models in the loop (``ModelVQFTogglingFilter``): diagnostics the core's, ``tau_acc``,
      ``tau_mag``, ``trust``, the predictions (``p_<state>``, ``eta_acc_x`` ...) and ``fallback``;
      the state holds the filter's, the feature window and the held prediction.
    """

    name = VQFTogglingFilter.name

    def __init__(self, rate: float, use_mag: bool = True, model=None):
        pm = load_pretrained(model)
        settings = pretrained_settings(use_mag, model)
        self.model_metadata = pm.metadata
        self.models = pm.models
        self.settings = settings
        self.runs_core_alone = settings.learning_off(use_mag)
        if self.runs_core_alone:
            self.runner = VQFCoreFilter(rate, settings.core_settings, use_mag=use_mag)
        else:
            self.runner = ModelVQFTogglingFilter(rate, settings, models=pm.models, use_mag=use_mag)

    def __repr__(self):
        path = "core alone" if self.runs_core_alone else "models in the loop"
        return f"{type(self).__name__}({path}: {self.runner!r})"

    fs = property(lambda self: self.runner.fs)
    Ts = property(lambda self: self.runner.Ts)
    use_mag = property(lambda self: self.runner.use_mag)
    state = property(lambda self: self.runner.state)
    quat = property(lambda self: self.runner.quat)
    diagnostic_names = property(lambda self: self.runner.diagnostic_names)
    last_diagnostics = property(lambda self: self.runner.last_diagnostics)

    def update(self, gyr, acc, mag=None, dt=None) -> np.ndarray:
        """One sample: gyr [rad/s], acc [m/s²], mag [µT] ``(3,)``, dt [s] (None: 1/rate). Returns the
        orientation ``(4,)``, [w, x, y, z], sensor -> ENU."""
        return self.runner.update(gyr, acc, mag, dt)

    def update_batch(self, gyr, acc, mag=None, dt=None) -> FilterOutput:
        """``(N, 3)`` samples (``update``'s units; dt scalar or ``(N,)``): a ``FilterOutput`` with
        ``.quat (N, 4)`` and the diagnostics of the path that runs (class docstring)."""
        return self.runner.update_batch(gyr, acc, mag, dt)

    def reset(self):
        """Forget everything (the filter's initial state; the feature window and held prediction too)."""
        self.runner.reset()

    def get_state(self) -> np.ndarray:
        """The whole state of the path that runs, flat ``(n,)``."""
        return self.runner.get_state()

    def set_state(self, state):
        """Restore what ``get_state`` returned."""
        self.runner.set_state(state)

    def set_quat(self, q):
        """Set the orientation ``(4,)`` (sensor -> ENU) and mark the filter initialised."""
        self.runner.set_quat(q)

    def state_dict(self) -> dict:
        """The filter's state by name."""
        return self.runner.state_dict()


def pretrained_settings(use_mag: bool = True, model=None) -> VQFTogglingSettings:
    """The learned settings of the portable model ``model`` (default: the shipped one) in 9D or 6D."""
    pm = load_pretrained(model)
    mode = mode_name("vqf_toggling", use_mag)
    if mode not in pm.gains:
        raise KeyError(f"{model or PRETRAINED_FILE}: no learned settings for {mode} (has {sorted(pm.gains)})")
    return settings_from_dict(VQFTogglingSettings, pm.gains[mode])


def portable_from_model_dir(model_dir, path, metadata: dict) -> Path:
    """Write the learned VQF of a ``togglecf train`` directory (its compiled models and the settings of
    ``VQF_MODES`` in its gains.json) as one portable file with ``metadata``."""
    doc = json.loads((Path(model_dir) / GAINS_FILE).read_text())
    gains = {m: doc[m]["settings"] for m in VQF_MODES if m in doc}
    for m in gains:  # the checks of a model directory's gains: format, feature schema of its models
        load_gains(model_dir, use_mag=MODES[m][1], kind="vqf_toggling")
    if not gains:
        raise KeyError(f"{model_dir}: no learned VQF settings ({', '.join(VQF_MODES)}) in {GAINS_FILE}")
    return save_portable(path, load_compiled_models(model_dir), gains, metadata)
