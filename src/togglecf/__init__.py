"""togglecf: a data-driven toggling-gain complementary filter for IMU orientation, on BROAD.

Conventions (see ``togglecf.core.quaternion``): quaternions ``[w, x, y, z]``, Hamilton product,
sensor -> earth, earth frame ENU; SI units (rad/s, m/s², µT); time series ``(N, 3)``/``(N, 4)``
float64, one sample a row; the sampling rate is always passed explicitly.
"""
import hashlib as _hashlib
import os as _os
import sys as _sys
from pathlib import Path as _Path

__version__ = "0.1.0"


#: the package's files whose content ``source_digest`` covers
_SOURCE_SUFFIXES = (".py", ".c", ".h", ".json", ".toml")


def source_digest(root=None) -> str:
    """sha256 (hex) of the content of every source file of the package (``root``: another tree),
    walked in sorted order: the key of the caches an edit must invalidate (numba's compiled kernels
    below, the results store of ``make run``)."""
    root = _Path(root) if root is not None else _Path(__file__).resolve().parent
    h = _hashlib.sha256()
    for p in sorted(f for f in root.rglob("*") if f.suffix in _SOURCE_SUFFIXES and f.is_file()):
        h.update(p.relative_to(root).as_posix().encode() + b"\0")
        h.update(p.read_bytes())
    return h.hexdigest()


def _numba_cache_dir() -> str:
    """numba's on-disk cache checks only the timestamp of a kernel's own file, not of the
    functions it inlines from other modules: after an edit of ``filters/base.py`` a cached
    ``ekf_step`` would run the old code. Keying the cache directory on the content of every source
    file of the package (``source_digest``) makes any change start a fresh cache."""
    base = _os.environ.get("XDG_CACHE_HOME") or _os.path.join(_os.path.expanduser("~"), ".cache")
    return _os.path.join(base, "togglecf", "numba", f"{__version__}-{source_digest()[:16]}")


if "NUMBA_CACHE_DIR" not in _os.environ:
    _os.environ["NUMBA_CACHE_DIR"] = _numba_cache_dir()
    # numba reads the variable when it is first imported; imported before togglecf (a script's own
    # ``from numba import njit`` first), it would cache the package's kernels beside their sources, keyed on
    # each kernel's own file only, and run stale code after an edit of a function it inlines from another file.
    # Its locator reads the setting when a kernel is decorated, after this
    if "numba" in _sys.modules:
        _sys.modules["numba"].core.config.CACHE_DIR = _os.environ["NUMBA_CACHE_DIR"]


def __getattr__(name):
    """``togglecf.LearnedVQF``: the pretrained learned VQF (``togglecf.toggling.pretrained``), imported
    on first use so that ``import togglecf`` stays light."""
    if name == "LearnedVQF":
        from togglecf.toggling.pretrained import LearnedVQF  # noqa: PLC0415 (lazy: a heavy import on first use)

        return LearnedVQF
    raise AttributeError(f"module 'togglecf' has no attribute {name!r}")
