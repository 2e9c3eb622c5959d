"""Pure foundations used by every layer: the quaternion conventions, atomic artifacts, configs,
logging, progress bars and the optional dependencies (``extras``). Imports nothing else of togglecf.

``togglecf.core.quaternion`` (numba) is not imported here: ``from togglecf.core import quaternion``
loads it where it is used, so that the command line starts without compiling anything."""
from togglecf.core.config import config_path, merge_settings, read_toml
from togglecf.core.extras import MissingExtraError, require
from togglecf.core.io import atomic_write_bytes, atomic_write_json, atomic_write_text, check_keys, file_sha256
from togglecf.core.log import setup_logging
from togglecf.core.progress import progress

__all__ = ["config_path", "merge_settings", "read_toml", "MissingExtraError", "require",
           "atomic_write_bytes", "atomic_write_json", "atomic_write_text", "check_keys", "file_sha256",
           "setup_logging", "progress"]
