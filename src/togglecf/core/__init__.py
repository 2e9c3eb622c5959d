"""Pure foundations used by every layer: the quaternion conventions, atomic artifacts, configs,
logging and progress bars. Imports nothing else of togglecf."""
from togglecf.core import quaternion
from togglecf.core.config import config_path, merge_settings, read_toml
from togglecf.core.io import atomic_write_bytes, atomic_write_json, atomic_write_text, check_keys, file_sha256
from togglecf.core.log import setup_logging
from togglecf.core.progress import progress

__all__ = ["quaternion", "config_path", "merge_settings", "read_toml", "atomic_write_bytes", "atomic_write_json",
           "atomic_write_text", "check_keys", "file_sha256", "setup_logging", "progress"]
