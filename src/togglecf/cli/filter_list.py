"""A comma-separated list of filter names on the command line (``evaluate --filters``, ``plot --filters``)
as validated registry specs: the learned filters of the list (``toggling``, ``vqf_toggling``) take the one
``--models DIR``, the others none. Imported by the commands that run filters, not by ``cli.parsers``."""
from __future__ import annotations

from togglecf.registry import FILTER_NAMES, LEARNED_VQF, TRAINED, FilterSpec, is_portable_file

__all__ = ["filter_names", "filter_specs"]


def filter_names(text: str, option: str = "--filters") -> list[str]:
    """``"learned_vqf, vqf,madgwick"`` -> the names, in order; a ``ValueError`` naming ``option`` for an empty
    list, an unknown name or one given twice."""
    names = [n.strip() for n in text.split(",") if n.strip()]
    if not names:
        raise ValueError(f"{option} names no filter")
    for k, name in enumerate(names):
        if name not in FILTER_NAMES:
            raise ValueError(f"unknown filter {name!r} in {option}; available: {', '.join(FILTER_NAMES)}")
        if name in names[:k]:
            raise ValueError(f"{option} names {name} twice")
    return names


def filter_specs(names: list[str], models: str | None, use_mag: bool, option: str = "--filters") -> list[FilterSpec]:
    """The specs of ``names``, ``models`` given to the learned filters among them (a portable model file,
    ``.npz``: to ``learned_vqf`` instead of the shipped model); refused (one line): a learned filter without
    ``models``, ``models`` without a learned filter."""
    if models and is_portable_file(models):
        if LEARNED_VQF not in names:
            raise ValueError(f"--models {models} is a portable model file, for {LEARNED_VQF}, and {option} names "
                             "it not")
        return [FilterSpec(n, models=models if n == LEARNED_VQF else None, use_mag=use_mag) for n in names]
    trained = [n for n in names if n in TRAINED]
    if trained and not models:
        raise ValueError(f"{option} {trained[0]} needs --models DIR (a `togglecf train` model directory)")
    if models and not trained:
        raise ValueError(f"--models DIR is for {' / '.join(TRAINED)}, and {option} names neither")
    return [FilterSpec(n, models=models if n in TRAINED else None, use_mag=use_mag) for n in names]
