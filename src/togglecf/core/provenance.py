"""Where a result came from: the code's commit, so that a generated table names the run that made
it (not a folder that is gone by the time anyone reads the table)."""
from __future__ import annotations

import subprocess
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path

__all__ = ["source_revision"]


def _git(args, cwd) -> str | None:
    try:
        out = subprocess.run(["git", *args], cwd=cwd, capture_output=True, text=True, timeout=10)
    except (OSError, subprocess.TimeoutExpired):
        return None
    return out.stdout.strip() if out.returncode == 0 else None


def source_revision(path=None) -> str:
    """The code a run used: ``"commit <hash>"`` (7 hex digits) for a git checkout of the package
    (``path``: the checkout, default the package's own directory), ``"commit <hash> with uncommitted changes"``
    when tracked files differ from it, else ``"togglecf <version>"`` (an installed wheel)."""
    where = Path(path) if path is not None else Path(__file__).resolve().parent
    commit = _git(["rev-parse", "--short=7", "HEAD"], where)
    if not commit:
        try:
            return f"togglecf {version('togglecf')}"
        except PackageNotFoundError:  # run from a source tree that is not a git checkout
            return "togglecf (unknown version)"
    dirty = _git(["status", "--porcelain", "--untracked-files=no"], where)
    return f"commit {commit}" + (" with uncommitted changes" if dirty else "")
