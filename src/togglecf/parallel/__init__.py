"""Execution backends: this process, a local process pool, or a Dask cluster; trials loaded where
the work runs."""
from togglecf.parallel.backend import (
                                       Backend,
                                       BackendError,
                                       DaskBackend,
                                       InlineBackend,
                                       LocalBackend,
                                       Outcome,
                                       Task,
                                       load_trial_cached,
                                       make_backend,
                                       run_tasks,
                                       sweep_chunk_size,
                                       trial_identity,
)

__all__ = ["Backend", "BackendError", "DaskBackend", "InlineBackend", "LocalBackend", "Outcome", "Task",
           "load_trial_cached", "make_backend", "run_tasks", "sweep_chunk_size", "trial_identity"]
