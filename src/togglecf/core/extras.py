"""The optional dependencies: which extra of ``pip install 'togglecf[EXTRA]'`` installs what, and the
one way the package imports them.

``pip install togglecf`` installs numpy, scipy, numba and h5py: every filter, the simulator, BROAD's
metrics, reading trial files (``.hdf5``, ``.mat``), the pretrained learned VQF (``togglecf.LearnedVQF``),
and the filter of a trained model directory in the loop
(``togglecf.toggling.load_toggling_filter``, the registry's learned filters: ``togglecf train``
stores the trees as ``inloop_forest.json``, read without XGBoost). The rest are extras
(``[project.optional-dependencies]`` in pyproject.toml):

* ``data``: pandas (the tables of ``evaluate``, ``tune`` and the
  study), tqdm (progress bars; without it there are none);
* ``train``: ``data`` + xgboost, scikit-learn (``togglecf train``; reading a model directory's
  XGBoost files, e.g. one trained before ``inloop_forest.json`` existed);
* ``export``: ``train`` + treelite, tl2cgen (``togglecf export``, ``togglecf prune``);
* ``plot``: ``data`` + matplotlib (``togglecf plot``, the study's figures);
* ``stream``: pyserial (``togglecf stream --port``; ``--input`` needs nothing);
* ``dask``: dask.distributed (``--backend dask``);
* ``vqf``: the reference VQF (dlaidig/vqf; the ``vqf`` filter of ``evaluate``, ``plot``, ``stream``: the
  study's baseline at its defaults);
* ``import``: qmt, the BROAD authors' toolbox (``togglecf import --reference``: clock synchronisation,
  IMU-to-marker and reference-frame alignment, magnetometer calibration; an import without a
  reference needs nothing);
* ``embedded``: unicorn, capstone (the Cortex-M4F cycle estimate of the exported C filters,
  ``togglecf.embedded.cycles``; with the system's ``arm-none-eabi-gcc``);
* ``all``: every extra.

An optional module is imported where it is used, through ``require`` (or bound at module level with
``deferred``, imported on first use): when it is missing, a ``MissingExtraError`` (an ``ImportError``)
says in one line which extra installs it; the command line prints that line (no traceback).
"""
from __future__ import annotations

import importlib
import importlib.util

__all__ = ["EXTRAS", "MissingExtraError", "missing_extra_message", "require", "check_extra", "deferred"]

#: extra -> the modules its commands import (those of the extras it includes too); pyproject.toml installs
#: them (tests/test_light_install.py checks the two agree). tqdm is left out: without it there are no bars.
EXTRAS = {
    "data": ("pandas",),
    "train": ("pandas", "xgboost", "sklearn"),
    "export": ("pandas", "xgboost", "sklearn", "treelite", "tl2cgen"),
    "plot": ("pandas", "matplotlib"),
    "stream": ("serial",),
    "dask": ("dask", "distributed"),
    "import": ("qmt",),
    "vqf": ("vqf",),
    "embedded": ("unicorn", "capstone"),
}


class MissingExtraError(ImportError):
    """An optional dependency is not installed; the message (one line) names the extra to install."""


def missing_extra_message(extra: str, what: str) -> str:
    """``"<what> needs the [<extra>] extra: pip install 'togglecf[<extra>]'"``."""
    if extra not in EXTRAS:
        raise ValueError(f"unknown extra {extra!r}; one of {sorted(EXTRAS)}")
    return f"{what} needs the [{extra}] extra: pip install 'togglecf[{extra}]'"


def require(module: str, extra: str, what: str):
    """``module`` imported, e.g. ``xgb = require("xgboost", extra="train", what="togglecf train")``.

    Raises ``MissingExtraError`` (``missing_extra_message``) when it, or a module it imports, is not
    installed; other import failures (a broken installation) propagate unchanged."""
    try:
        return importlib.import_module(module)
    except ModuleNotFoundError as exc:
        raise MissingExtraError(missing_extra_message(extra, what), name=exc.name) from exc


def check_extra(extra: str, what: str) -> None:
    """Raise ``MissingExtraError`` unless every module of ``EXTRAS[extra]`` is installed (found, not
    imported: cheap, for a command to refuse at once rather than after minutes of work)."""
    for module in EXTRAS[extra]:
        try:
            found = importlib.util.find_spec(module) is not None
        except (ImportError, ValueError):  # a finder that refuses it; a module left half-imported
            found = False
        if not found:
            raise MissingExtraError(missing_extra_message(extra, what), name=module)


class _Deferred:
    """Stands for a module bound at import time; the first attribute access imports it (``require``)."""

    def __init__(self, module: str, extra: str, what: str):
        self.__dict__["_args"] = (module, extra, what)

    def __getattr__(self, name):
        return getattr(require(*self.__dict__["_args"]), name)

    def __repr__(self):
        return f"<deferred module {self.__dict__['_args'][0]!r}>"


def deferred(module: str, extra: str, what: str):
    """A module-level name for an optional module, imported (``require``) on first attribute access:
    ``pd = deferred("pandas", extra="data", what="the study report")`` keeps the importing module
    importable without the extra; using ``pd.DataFrame`` without it raises ``MissingExtraError``."""
    missing_extra_message(extra, what)  # a typo in the extra fails at import, not on first use
    return _Deferred(module, extra, what)
