"""One logging set-up for the whole package: progress and diagnostics go to the ``togglecf``
logger, which writes to stderr; results (tables, TAGPs) are printed to stdout by the commands.

Library code only calls ``logging.getLogger(__name__)``; the command line (and ``make run``)
calls ``setup_logging`` once. Without it, a library user sees the messages through Python's
default (warnings and above) or configures ``logging`` as they like.
"""
from __future__ import annotations

import logging
import sys

__all__ = ["setup_logging", "configured_level", "follow_parent_logging"]

_HANDLER_NAME = "togglecf-stderr"


class _StderrHandler(logging.StreamHandler):
    """Writes to whatever ``sys.stderr`` is when a message is logged (pytest, notebooks and
    ``contextlib.redirect_stderr`` replace it after ``setup_logging`` ran)."""

    def __init__(self):
        super().__init__(sys.stderr)

    @property
    def stream(self):
        return sys.stderr

    @stream.setter
    def stream(self, value):  # the base class assigns it; the current sys.stderr is always used
        pass


def setup_logging(level: int = logging.INFO) -> logging.Logger:
    """Send the ``togglecf`` logger's messages (``level`` and above) to stderr as plain lines;
    idempotent (one handler however often it is called)."""
    logger = logging.getLogger("togglecf")
    logger.setLevel(level)
    if not any(getattr(h, "name", None) == _HANDLER_NAME for h in logger.handlers):
        handler = _StderrHandler()
        handler.set_name(_HANDLER_NAME)
        handler.setFormatter(logging.Formatter("%(message)s"))
        logger.addHandler(handler)
    logger.propagate = False
    return logger


def configured_level() -> int | None:
    """The level ``setup_logging`` set in this process, ``None`` when it was not called: what a task
    started in a fresh worker process (``forkserver``, ``spawn``) passes on, so that its progress
    reaches the same stderr (``follow_parent_logging``)."""
    logger = logging.getLogger("togglecf")
    if any(getattr(h, "name", None) == _HANDLER_NAME for h in logger.handlers):
        return logger.level
    return None


def follow_parent_logging(level: int | None) -> None:
    """In a worker: ``setup_logging(level)`` when the parent had it (``configured_level``), else nothing."""
    if level is not None:
        setup_logging(level)
