"""TOML configs: the packaged defaults, reading, and the one precedence rule.

The default configs ship inside the package (``togglecf/configs/*.toml``), so an installed
``togglecf`` (not only a checkout) finds them. Precedence, everywhere: command-line flags over
the config file over the built-in defaults (``merge_settings``).
"""
from __future__ import annotations

import tomllib
from importlib import resources
from pathlib import Path

__all__ = ["config_path", "read_toml", "merge_settings", "RUN_DEFAULTS", "BACKENDS", "load_run_section"]

#: execution backends (``togglecf.parallel``): this machine's processes, or a Dask cluster
BACKENDS = ("local", "dask")

#: ``[run]`` of a training config: run name, seed, threads, CV folds, trial selection, top-k features,
#: where CV folds / per-trial features / sweeps run (``togglecf.parallel``), and the data directories
#: (``data``: "" for the default location, a directory, or a list of them; ``--data`` overrides it), and the
#: out-of-range fallback threshold stored with the models (``learn.ranges``; 1 disables the fallback)
RUN_DEFAULTS = {"name": "default", "seed": 0, "nthread": 2, "cv_folds": 5, "trials": "all", "max_features": 0,
                "backend": "local", "scheduler": "", "retries": 2, "chunk_size": -1, "distributed_fit": False,
                "data": "", "max_out_of_range": 0.2}


def config_path(name: str) -> Path:
    """Path of a packaged default config (``"default.toml"``, ``"study.toml"``)."""
    path = Path(str(resources.files("togglecf") / "configs" / name))
    if not path.is_file():
        raise FileNotFoundError(f"no packaged config {name!r} (looked in {path.parent})")
    return path


def read_toml(source) -> dict:
    """A TOML file as a dict (a dict is returned as a copy of its tables); errors name the file."""
    if isinstance(source, dict):
        return {k: dict(v) if isinstance(v, dict) else v for k, v in source.items()}
    path = Path(source)
    try:
        with open(path, "rb") as f:
            return tomllib.load(f)
    except FileNotFoundError:
        raise FileNotFoundError(f"{path}: config file not found") from None
    except tomllib.TOMLDecodeError as exc:
        raise ValueError(f"{path}: not valid TOML: {exc}") from None


def merge_settings(defaults: dict, config: dict | None = None, flags: dict | None = None, what: str = "config") -> dict:
    """``defaults`` overridden by ``config`` (unknown keys refused) overridden by the ``flags``
    that are not ``None`` (command-line options left unset)."""
    config = dict(config or {})
    unknown = sorted(set(config) - set(defaults))
    if unknown:
        raise ValueError(f"{what}: unknown key(s) {unknown}; known: {sorted(defaults)}")
    out = {**defaults, **config}
    out.update({k: v for k, v in (flags or {}).items() if v is not None and k in defaults})
    return out


def load_run_section(source=None, flags: dict | None = None) -> dict:
    """The ``[run]`` table of a config (default: the packaged ``default.toml``) with defaults filled
    in and ``flags`` over it; the backend name checked."""
    raw = read_toml(config_path("default.toml") if source is None else source)
    run = merge_settings(RUN_DEFAULTS, raw.get("run", {}), flags, what="config [run]")
    if run["backend"] not in BACKENDS:
        raise ValueError(f"config [run]: backend must be one of {list(BACKENDS)}, got {run['backend']!r}")
    data = run["data"]
    if not (isinstance(data, str) or (isinstance(data, list) and all(isinstance(d, str) and d for d in data))):
        raise ValueError(f"config [run]: data must be a directory or a list of directories, got {data!r}")
    return run
