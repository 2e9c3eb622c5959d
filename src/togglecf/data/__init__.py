"""Recordings in BROAD's layout: the trial index, loading with checks, finding and downloading data."""
from togglecf.data.broad import (
                                 BROAD_URL,
                                 GRAVITY,
                                 DataError,
                                 DataNotFoundError,
                                 DatasetIndex,
                                 MultiIndex,
                                 Trial,
                                 load_trial,
                                 open_index,
                                 resolve_data_dir,
                                 resolve_data_dirs,
)
from togglecf.data.download import download_broad

__all__ = ["BROAD_URL", "GRAVITY", "DataError", "DataNotFoundError", "DatasetIndex", "MultiIndex", "Trial",
           "load_trial", "open_index", "resolve_data_dir", "resolve_data_dirs", "download_broad"]
