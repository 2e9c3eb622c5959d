"""Progress bars on stderr for long work (quiet when stderr is not a terminal, unless forced)."""
from __future__ import annotations

import os
import sys

from tqdm.auto import tqdm

__all__ = ["progress"]


def progress(iterable, **kwargs):
    """``tqdm`` with the project's defaults. ``TOGGLECF_PROGRESS=0`` disables it, ``=1`` forces it."""
    flag = os.environ.get("TOGGLECF_PROGRESS")
    disable = (flag == "0") or (flag != "1" and not sys.stderr.isatty())
    return tqdm(iterable, file=sys.stderr, disable=disable, dynamic_ncols=True, **kwargs)
