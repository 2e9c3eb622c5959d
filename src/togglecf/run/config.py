"""The training and study configs: loading with defaults, validation and the packaged defaults.

Training config (``togglecf train``, TOML; default ``togglecf/configs/default.toml``): sections
``[run]`` (``core.config.RUN_DEFAULTS``), ``[labels]``, ``[features]``, ``[classifier]``,
``[regressor]``, ``[gains]``; unknown sections and keys are refused with their names. ``[gains.vqf]`` is the
learned VQF's search (``VQFGainSearch``); ``[gains.relearn]`` the values ``togglecf train --from-pretrained``
searches in place of ``[gains.vqf]``'s (``relearn_search``); ``[gains.pretrained]`` those the pretrained recipe,
trained on several sensors, searches in their place (``pretrained_config``).
"""
from __future__ import annotations

from togglecf.core.config import config_path, load_run_section, read_toml
from togglecf.core.io import check_keys
from togglecf.features.windows import FeatureSettings
from togglecf.learn.labels import LabelSettings
from togglecf.learn.models import MotionClassifier, NoiseRegressor
from togglecf.toggling.gains import MODES, GainSearch, VQFGainSearch

__all__ = ["DEFAULT_CONFIG", "load_config", "SECTIONS", "GAIN_KEYS", "RELEARN_DEFAULTS", "relearn_search",
           "PRETRAINED_DEFAULTS", "pretrained_config"]

DEFAULT_CONFIG = config_path("default.toml")
SECTIONS = ("run", "labels", "features", "classifier", "regressor", "gains")
#: keys of ``[gains]`` that are not the toggling CF's search grids: whether and for which modes (``toggling.gains.MODES``)
#: gains are learned, ``vqf``, the sub-table of the VQF core's search (``VQFGainSearch``), and ``relearn``, what the
#: re-learning on one sensor searches in its place (``relearn_search``), and ``pretrained``, what the pretrained recipe
#: searches in its place (``pretrained_config``)
GAIN_KEYS = ("learn", "modes", "vqf", "relearn", "pretrained")
#: ``[gains.relearn]``'s values where a config has none: σ_f [µT], the scale of the learned VQF's back-off on the
#: field's change (step 3b of ``filters.vqf_toggling``; 0: off), searched when re-learning on one sensor's recordings
#: (a magnetic environment and magnetometer of its own), not when training on several (``[gains.vqf]``: off)
RELEARN_DEFAULTS = {"field_change_scale": (0.0, 10.0, 20.0, 50.0)}


#: ``[gains.pretrained]``'s values where a config has none: the pretrained recipe, trained on several sensors
#: (``run.pretrained``, and ``run.lodo`` that checks it leaving each dataset out), keeps τ_acc at the core's 3 s in
#: every state (a per-state τ_acc learned on some sensors did not travel to another, and a perfect motion classifier
#: would gain nothing on any developer dataset: the headroom's true-labels rows) and takes a step where it lowers the
#: mean over the training datasets with none of them above learning off (``gains`` objective
#: ``mean_dataset_log_ratio``: with the worst dataset's objective, which keeps a step only where every training
#: dataset gains beyond its scatter, the model learned nothing, while the heading back-off on the predicted
#: disturbance, learned on two sensors, helped the third where it was BROAD or the Nexus 5)
PRETRAINED_DEFAULTS = {"tau_acc": (3.0,), "objective": "mean_dataset_log_ratio"}


def pretrained_config(cfg: dict) -> dict:
    """The training config of the pretrained recipe from a loaded config ``cfg`` (``load_config``): a copy whose
    ``[gains.vqf]`` has ``PRETRAINED_DEFAULTS`` and then each key of ``[gains.pretrained]`` in place."""
    gains = cfg["gains"]
    pretrained = check_keys(VQFGainSearch, dict(gains.get("pretrained", {})), "[gains.pretrained]")
    return {**cfg, "gains": {**gains, "vqf": {**gains.get("vqf", {}), **PRETRAINED_DEFAULTS, **pretrained}}}


def relearn_search(cfg: dict) -> VQFGainSearch:
    """The search of ``togglecf train --from-pretrained`` for a loaded config ``cfg`` (``load_config``): ``[gains.vqf]``
    with each key of ``[gains.relearn]`` (where it has none: ``RELEARN_DEFAULTS``) in its place."""
    gains = cfg["gains"]
    relearn = check_keys(VQFGainSearch, dict(gains.get("relearn", {})), "[gains.relearn]")
    return VQFGainSearch.from_dict({**gains.get("vqf", {}), **RELEARN_DEFAULTS, **relearn})


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
    relearn_search(cfg)  # [gains.relearn]'s keys are the VQF search's
    VQFGainSearch.from_dict(pretrained_config(cfg)["gains"]["vqf"])  # and [gains.pretrained]'s
    bad_modes = sorted(set(cfg["gains"].get("modes", ())) - set(MODES))
    if bad_modes:
        raise ValueError(f"{what} [gains] modes: unknown {bad_modes}; known: {list(MODES)}")
    for sec, cls in (("classifier", MotionClassifier), ("regressor", NoiseRegressor)):
        allowed = set(cls.param_names()) - {"nthread", "seed", "target"}
        unknown = sorted(set(cfg[sec]) - allowed)
        if unknown:
            raise ValueError(f"{what} [{sec}]: unknown key(s) {unknown}; known: {sorted(allowed)}")
    return cfg
