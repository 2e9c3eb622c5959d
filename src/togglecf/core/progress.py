"""Progress bars on stderr for long work (quiet when stderr is not a terminal, unless forced). tqdm is
optional (the ``data`` extra): without it the work runs without bars."""
from __future__ import annotations

import os
import sys

from togglecf.core.extras import MissingExtraError, require

__all__ = ["progress"]


def progress(iterable=None, **kwargs):
    """``tqdm`` with the project's defaults. ``TOGGLECF_PROGRESS=0`` disables it, ``=1`` forces it.
    Without tqdm: the iterable itself, in an object that also takes ``with``, ``update`` and ``close``."""
    flag = os.environ.get("TOGGLECF_PROGRESS")
    disable = (flag == "0") or (flag != "1" and not sys.stderr.isatty())
    try:
        tqdm = require("tqdm.auto", extra="data", what="progress bars").tqdm
    except MissingExtraError:
        return _NoBar(iterable)
    return tqdm(iterable, file=sys.stderr, disable=disable, dynamic_ncols=True, **kwargs)


class _NoBar:
    """What ``progress`` returns without tqdm: iterates, and the bar methods the package calls do nothing."""

    def __init__(self, iterable=None):
        self.iterable = iterable

    def __iter__(self):
        return iter(self.iterable if self.iterable is not None else ())

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        return False

    def update(self, n=1):
        pass

    def close(self):
        pass

    def set_postfix(self, *args, **kwargs):
        pass

    def set_description(self, *args, **kwargs):
        pass
