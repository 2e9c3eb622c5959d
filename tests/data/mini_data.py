"""Which mini directory the tests (``tests/conftest.py``) and the benchmarks' quick modes
(``pipelines/bench_common.py``) use: the real cuts or the synthetic stand-in (README.md here).

``TOGGLECF_MINI``: unset (or ``auto``): the real cuts ``broad_mini/`` (cut from BROAD on first use)
when BROAD is found, otherwise the synthetic trials ``synthetic_mini/`` (written on first use); under
``TOGGLECF_REQUIRE_DATA=1`` BROAD is required instead. ``broad``: the real cuts or
``DataNotFoundError``. ``synthetic``: the synthetic trials, even where BROAD is found (and under
``TOGGLECF_REQUIRE_DATA=1``).
"""
from __future__ import annotations

import os
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent
if str(HERE) not in sys.path:
    sys.path.insert(0, str(HERE))

import make_broad_mini  # noqa: E402
import make_synthetic_mini  # noqa: E402

from togglecf.data.broad import DataNotFoundError  # noqa: E402

KINDS = ("broad", "synthetic")
BROAD_DIR = make_broad_mini.OUT
SYNTHETIC_DIR = make_synthetic_mini.OUT


def requested() -> str:
    """``TOGGLECF_MINI``: ``auto`` (also when unset), ``broad`` or ``synthetic``."""
    want = os.environ.get("TOGGLECF_MINI", "").strip().lower() or "auto"
    if want not in ("auto",) + KINDS:
        raise ValueError(f"TOGGLECF_MINI={want!r}: expected 'broad', 'synthetic' or 'auto' (or unset)")
    return want


def mini_dir() -> tuple[str, Path]:
    """``(kind, directory)``: ``kind`` is ``"broad"`` or ``"synthetic"``, the directory exists. Raises
    ``DataNotFoundError`` when the real cuts are needed (``TOGGLECF_MINI=broad``, or
    ``TOGGLECF_REQUIRE_DATA=1`` without ``TOGGLECF_MINI=synthetic``) and BROAD is nowhere."""
    want = requested()
    if want == "synthetic":
        return "synthetic", make_synthetic_mini.ensure(SYNTHETIC_DIR)
    try:
        return "broad", make_broad_mini.ensure(BROAD_DIR)
    except DataNotFoundError:
        if want == "broad" or os.environ.get("TOGGLECF_REQUIRE_DATA") == "1":
            raise
    return "synthetic", make_synthetic_mini.ensure(SYNTHETIC_DIR)
