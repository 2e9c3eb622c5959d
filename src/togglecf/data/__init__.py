"""Recordings in BROAD's layout: the trial index, loading with checks, finding and downloading data."""
from togglecf.data.broad import (
                                 BROAD_URL,
                                 GRAVITY,
                                 DataError,
                                 DataNotFoundError,
                                 DatasetIndex,
                                 Trial,
                                 load_trial,
                                 resolve_data_dir,
)
from togglecf.data.download import download_broad

__all__ = ["BROAD_URL", "GRAVITY", "DataError", "DataNotFoundError", "DatasetIndex", "Trial", "load_trial",
           "resolve_data_dir", "download_broad"]
