"""The tree libraries' chatter kept out of a command's output (``togglecf export``, ``togglecf prune``).

TL2cgen embeds an older Treelite than the one that writes the checkpoints, and says so three lines at a
time for every model it loads, straight from its native code to the process's stderr; its compiler logs
"Parallel compilation disabled" to stdout for every model; XGBoost and Treelite add version and
deprecation warnings. None of it is about the user's input (the versions are documented in
``togglecf.embedded.forest_export``). ``library_noise_filtered`` drops exactly
those lines for the duration of a command: Python warnings from those libraries' modules, their loggers
below ERROR, and, on the file descriptors, their native log lines; a line that says "error" is always
kept, and errors raise exceptions anyway. Standard library only: imported by ``cli.parsers``.
"""
from __future__ import annotations

import logging
import os
import re
import sys
import threading
import warnings
from contextlib import contextmanager

__all__ = ["LIBRARIES", "is_library_noise", "silence_library_warnings", "library_noise_filtered"]

#: the libraries whose version and deprecation chatter is dropped
LIBRARIES = ("treelite", "tl2cgen", "xgboost")
#: a native log line of those libraries: "[15:12:43] /path/src/serializer.cc:202: ..." (XGBoost: "[..] WARNING: ...")
_NATIVE_LOG = re.compile(r"^\[\d\d:\d\d:\d\d\] (WARNING: )?\S+\.(cc|h|cpp|cu):\d+: ")
#: the continuation lines of Treelite's version warning (no prefix of their own)
_CONTINUATION = re.compile(r"^(Currently running Treelite version|The model checkpoint was generated from Treelite "
                           r"version) [\d.]+\s*$")
_MODULES = r"^(" + "|".join(LIBRARIES) + r")(\.|$)"


def is_library_noise(line: str) -> bool:
    """Whether an output line is a native log line of the tree libraries, or the continuation of Treelite's
    version warning, and not an error."""
    if "error" in line.lower():
        return False
    return bool(_NATIVE_LOG.match(line) or _CONTINUATION.match(line))


def silence_library_warnings() -> None:
    """Python warnings raised in the libraries' modules, XGBoost's native warnings passed on as Python
    warnings, and the libraries' loggers below ERROR: off (call inside ``warnings.catch_warnings``)."""
    warnings.filterwarnings("ignore", module=_MODULES)
    warnings.filterwarnings("ignore", message=_NATIVE_LOG.pattern.lstrip("^"))
    for name in LIBRARIES:
        logging.getLogger(name).setLevel(logging.ERROR)


class _LineFilter:
    """A text stream that passes on whole lines that are not library noise (``sys.stdout``: TL2cgen's
    log callback prints there)."""

    def __init__(self, stream):
        self._stream, self._partial = stream, ""

    def write(self, text: str) -> int:
        lines = (self._partial + text).split("\n")
        self._partial = lines.pop()
        for line in lines:
            if not is_library_noise(line):
                self._stream.write(line + "\n")
        return len(text)

    def flush(self) -> None:
        if self._partial and not is_library_noise(self._partial):
            self._stream.write(self._partial)
        self._partial = ""
        self._stream.flush()

    def __getattr__(self, name):
        return getattr(self._stream, name)


def _forward(read_fd: int, write_fd: int) -> None:
    """Copy lines from ``read_fd`` to ``write_fd`` until EOF, without the library noise."""
    with os.fdopen(read_fd, "rb") as pipe, os.fdopen(write_fd, "wb", buffering=0) as out:
        for line in pipe:
            if not is_library_noise(line.decode("utf-8", "replace")):
                out.write(line)


@contextmanager
def _fd_filtered(fd: int):
    """``fd`` (2: what native code writes to stderr) through a pipe whose lines are filtered on the way."""
    sys.stderr.flush()
    saved = os.dup(fd)
    read_fd, write_fd = os.pipe()
    os.dup2(write_fd, fd)
    os.close(write_fd)
    thread = threading.Thread(target=_forward, args=(read_fd, os.dup(saved)), daemon=True)
    thread.start()
    try:
        yield
    finally:
        sys.stderr.flush()
        os.dup2(saved, fd)  # the pipe's last write end closes: the thread reads to EOF and ends
        os.close(saved)
        thread.join(timeout=10)


@contextmanager
def library_noise_filtered():
    """The tree libraries' version and deprecation chatter dropped from Python warnings, their loggers,
    ``sys.stdout`` and file descriptor 2 while the block runs; everything else passes unchanged."""
    stdout = sys.stdout
    with warnings.catch_warnings(), _fd_filtered(2):
        silence_library_warnings()
        sys.stdout = _LineFilter(stdout)
        try:
            yield
        finally:
            sys.stdout.flush()
            sys.stdout = stdout
