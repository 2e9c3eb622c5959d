"""The pretrained learned VQF the package ships: ``LearnedVQF(rate)`` runs it with no training, in the
style of ``vqf.VQF(Ts)``::

    import togglecf
    f = togglecf.LearnedVQF(100.0)                       # rate [Hz]; use_mag=False: 6D
    quat = f.update_batch(gyr, acc, mag).quat             # (N, 4) [w, x, y, z], sensor -> ENU

The model (``pretrained/learned_vqf.npz``: the compiled forest, the feature settings and ranges, and
the learned 9D and 6D settings; ``learn.portable``) and its model card (``pretrained/MODEL_CARD.md``:
data, rates, sensors, held-out numbers, limits, licences) are made by ``make run`` (step 5:
``pipelines/main.py``) and copied into the package by ``pipelines/ship_pretrained.py`` only when
the recipe passes the no-harm check on every dataset left out. Reading it needs numpy alone.
"""
from __future__ import annotations

import json
from pathlib import Path

from togglecf.filters.vqf_toggling import VQFTogglingSettings
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


class LearnedVQF(ModelVQFTogglingFilter):
    """The pretrained learned VQF at ``rate`` [Hz] (9D, or 6D with ``use_mag=False``): the VQF core whose
    time constants the shipped models set per sample (``filters.vqf_toggling``). ``update(gyr, acc, mag)``
    returns the orientation ``(4,)``; ``update_batch`` returns a ``FilterOutput`` with ``.quat (N, 4)``
    and the diagnostics; ``get_state`` / ``set_state`` save and restore everything (filter, feature
    window, held prediction). Units: gyr rad/s, acc m/s², mag µT. ``model``: another portable file
    (``learn.portable``) instead of the shipped one."""

    def __init__(self, rate: float, use_mag: bool = True, model=None):
        pm = load_pretrained(model)
        super().__init__(rate, pretrained_settings(use_mag, model), models=pm.models, use_mag=use_mag)
        self.model_metadata = pm.metadata


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
