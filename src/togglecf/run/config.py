"""The training and study configs: loading with defaults, validation and the packaged defaults.

Training config (``togglecf train``, TOML; default ``togglecf/configs/default.toml``): sections
``[run]`` (``core.config.RUN_DEFAULTS``), ``[labels]``, ``[features]``, ``[classifier]``,
``[regressor]``, ``[gains]``; unknown sections and keys are refused with their names.
"""
from __future__ import annotations

from togglecf.core.config import config_path, load_run_section, read_toml
from togglecf.features.windows import FeatureSettings
from togglecf.learn.labels import LabelSettings
from togglecf.learn.models import MotionClassifier, NoiseRegressor
from togglecf.toggling.gains import MODES, GainSearch, VQFGainSearch

__all__ = ["DEFAULT_CONFIG", "load_config", "SECTIONS", "GAIN_KEYS"]

DEFAULT_CONFIG = config_path("default.toml")
SECTIONS = ("run", "labels", "features", "classifier", "regressor", "gains")
#: keys of ``[gains]`` that are not the toggling CF's search grids: whether and for which modes (``toggling.gains.MODES``)
#: gains are learned, and ``vqf``, the sub-table of the VQF core's search (``VQFGainSearch``)
GAIN_KEYS = ("learn", "modes", "vqf")


def load_config(source=None) -> dict:
    """Config dict from a TOML path (or an already parsed dict), defaults filled in, unknown keys refused."""
    raw = read_toml(DEFAULT_CONFIG if source is None else source)
    what = "config" if isinstance(source, dict) or source is None else str(source)
    bad = sorted(set(raw) - set(SECTIONS))
    if bad:
        raise ValueError(f"{what}: unknown section(s) {bad}; expected {list(SECTIONS)}")
    cfg = {s: dict(raw.get(s, {})) for s in SECTIONS}
    cfg["run"] = load_run_section({"run": cfg["run"]})
    LabelSettings.from_dict({**cfg["labels"], "seed": cfg["run"]["seed"]})  # validate early
    FeatureSettings.from_dict(cfg["features"])
    GainSearch.from_dict({k: v for k, v in cfg["gains"].items() if k not in GAIN_KEYS})
    VQFGainSearch.from_dict(cfg["gains"].get("vqf", {}))
    bad_modes = sorted(set(cfg["gains"].get("modes", ())) - set(MODES))
    if bad_modes:
        raise ValueError(f"{what} [gains] modes: unknown {bad_modes}; known: {list(MODES)}")
    for sec, cls in (("classifier", MotionClassifier), ("regressor", NoiseRegressor)):
        allowed = set(cls.param_names()) - {"nthread", "seed", "target"}
        unknown = sorted(set(cfg[sec]) - allowed)
        if unknown:
            raise ValueError(f"{what} [{sec}]: unknown key(s) {unknown}; known: {sorted(allowed)}")
    return cfg
