"""Where work runs: a local process pool (default) or a dask.distributed cluster.

One small interface for ``tune``, ``evaluate`` and ``train``::

    with make_backend("dask", scheduler="tcp://HOST:8786") as be:
        for out in be.run(fn, [(key, args), ...], desc="tune"):   # streams as tasks finish
            out.key, out.value, out.error                         # error: the exception, or None

* ``LocalBackend(jobs)``: a fork ``ProcessPoolExecutor`` on ``jobs`` processes (default all cores;
  ``start_method="forkserver"`` for tasks that train models, see the class);
  ``jobs=1`` (or a single task) runs in this process, in task order. No extra services.
* ``DaskBackend(scheduler)``: ``client.submit(fn, *args, retries=N)`` per task and
  ``distributed.as_completed``. A task lost with a worker is rescheduled by the scheduler (up to
  ``distributed.scheduler.allowed-failures`` times, then it fails with ``KilledWorker``); a task that
  raises is retried ``retries`` times. Failures come back as outcomes with ``error`` set; the caller
  decides whether to raise or report them.

Task functions must be importable module-level functions (they are pickled by reference). They get
paths and names, not arrays: trials are loaded where the task runs (``load_trial_cached``).
"""
from __future__ import annotations

import multiprocessing as mp
import os
from concurrent.futures import ProcessPoolExecutor
from concurrent.futures import as_completed as _cf_as_completed
from dataclasses import dataclass
from pathlib import Path

from togglecf.core.config import BACKENDS
from togglecf.core.progress import progress
from togglecf.data.broad import DatasetIndex, open_index

__all__ = ["BACKENDS", "BackendError", "Outcome", "Task", "Backend", "LocalBackend", "InlineBackend", "DaskBackend",
           "make_backend", "run_tasks", "load_trial_cached", "trial_identity", "data_location", "DASK_INSTALL_HINT"]

DASK_INSTALL_HINT = "pip install 'togglecf[dask]'"


CONNECT_TIMEOUT_S = 10.0  # seconds to wait for the Dask scheduler
#: connection attempts when distributed's handshake fails its own check (``_connect``)
CONNECT_ATTEMPTS = 2


def _connect(client_cls, scheduler, timeout: float):
    """``client_cls(scheduler, timeout=timeout)`` (a ``distributed.Client``), once more when its handshake
    fails distributed's own assertion (``Client._ensure_connected`` expects exactly one message as the
    scheduler's first reply; it got another once in the test suite, on a loaded machine); a second failure is
    a ``ValueError`` (reported as an unreachable scheduler)."""
    for attempt in range(1, CONNECT_ATTEMPTS + 1):
        try:
            return client_cls(scheduler, timeout=timeout)
        except AssertionError:
            if attempt == CONNECT_ATTEMPTS:
                raise ValueError(f"the scheduler's handshake failed {CONNECT_ATTEMPTS} times") from None


class BackendError(ValueError):
    """The backend cannot start (dask not installed, scheduler unreachable, bad settings)."""


@dataclass
class Outcome:
    """One finished task: ``value`` on success, else ``error`` (the exception)."""

    key: object
    value: object = None
    error: BaseException | None = None


@dataclass(frozen=True)
class Task:
    """One task of ``run_tasks``: ``fn(*args)`` under ``key``; ``fn`` a module-level function."""

    key: object
    fn: object
    args: tuple = ()


def _call(fn, *args):
    """The one task function of ``run_tasks``: ``Backend.run`` takes one function, this lets tasks differ."""
    return fn(*args)


def run_tasks(backend: "Backend", tasks, desc=None, unit="task") -> dict:
    """Run ``tasks`` (``Task``s, of any functions) on ``backend``, in the order given (put the longest
    first: a local pool starts them in that order); returns key -> value once every task is done, and
    raises the first failure. What lets one pool run several steps' tasks at once: the held-out study's
    folds beside the left-out datasets of ``make run``, so no worker waits for the last task of a step."""
    tasks = list(tasks)
    done = {}
    for outcome in backend.run(_call, [(t.key, (t.fn, *t.args)) for t in tasks], desc=desc, unit=unit):
        if outcome.error is not None:
            raise outcome.error
        done[outcome.key] = outcome.value
    return {t.key: done[t.key] for t in tasks}


class Backend:
    """Base class: ``run`` streams outcomes as tasks finish; a context manager closes it."""

    name = "base"
    workers = 1

    def run(self, fn, tasks, desc=None, unit="task"):
        raise NotImplementedError

    def scatter(self, obj):
        """A handle to pass ``obj`` to many tasks (the object itself locally, a future on Dask)."""
        return obj

    def close(self):
        pass

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    def describe(self) -> str:
        return f"{self.name} ({self.workers} worker{'s' if self.workers != 1 else ''})"


def _inline(fn, tasks, desc, unit):
    for key, args in progress(tasks, desc=desc, unit=unit):
        try:
            value = fn(*args)
        except Exception as exc:  # reported to the caller, which raises or reports it
            yield Outcome(key, None, exc)
        else:
            yield Outcome(key, value, None)


class InlineBackend(Backend):
    """Every task in this process, in order (debugging, profiling, work that threads itself)."""

    name = "inline"

    def run(self, fn, tasks, desc=None, unit="task"):
        yield from _inline(fn, list(tasks), desc, unit)


class LocalBackend(Backend):
    """A process pool on ``jobs`` processes (default: all cores).

    ``start_method``: ``"fork"`` (default) lets the workers inherit the parent's compiled kernels and
    loaded data; ``"forkserver"`` starts them from a clean server process, for tasks that train
    models: XGBoost's OpenMP runtime hangs in a child forked from a process that has already used it
    (the study's folds and the left-out datasets train, and ``make run`` trains before it forks)."""

    name = "local"
    START_METHODS = ("fork", "forkserver", "spawn")

    def __init__(self, jobs: int | None = None, start_method: str = "fork"):
        self.workers = int(jobs or os.cpu_count() or 1)
        if self.workers < 1:
            raise BackendError(f"jobs must be >= 1, got {jobs}")
        if start_method not in self.START_METHODS:
            raise BackendError(f"start_method must be one of {list(self.START_METHODS)}, got {start_method!r}")
        self.start_method = start_method

    def run(self, fn, tasks, desc=None, unit="task"):
        tasks = list(tasks)
        # a daemonic process (a Dask worker) may not start a pool: its tasks run in it, in order
        if self.workers == 1 or len(tasks) <= 1 or mp.current_process().daemon:
            yield from _inline(fn, tasks, desc, unit)
            return
        context = mp.get_context(self.start_method)
        with ProcessPoolExecutor(max_workers=min(self.workers, len(tasks)), mp_context=context) as pool:
            futs = {pool.submit(fn, *args): key for key, args in tasks}
            try:
                for fut in progress(_cf_as_completed(futs), total=len(futs), desc=desc, unit=unit):
                    exc = fut.exception()
                    yield Outcome(futs[fut], None if exc else fut.result(), exc)
            finally:
                for fut in futs:
                    fut.cancel()


class DaskBackend(Backend):
    """Tasks on a dask.distributed cluster: ``scheduler`` is an address (``tcp://HOST:8786``) or a
    ``distributed.Client`` (then it is not closed here)."""

    name = "dask"

    def __init__(self, scheduler, retries: int = 2, timeout: float | None = None):
        try:
            from distributed import Client
        except ImportError:
            raise BackendError(f"--backend dask needs dask.distributed, which is not installed: "
                               f"{DASK_INSTALL_HINT}") from None
        self.retries = int(retries)
        timeout = CONNECT_TIMEOUT_S if timeout is None else timeout
        self._own = not isinstance(scheduler, Client)
        if not self._own:
            self.client = scheduler
        else:
            if not scheduler:
                raise BackendError("--backend dask needs --scheduler tcp://HOST:8786 (or [run] scheduler in the "
                                   "config); start a scheduler with `dask scheduler` and workers with "
                                   "`dask worker tcp://HOST:8786`")
            try:
                self.client = _connect(Client, scheduler, timeout)
            except (OSError, TimeoutError, ValueError) as exc:
                raise BackendError(f"cannot reach Dask scheduler at {scheduler}: start one with `dask scheduler` "
                                   f"and workers with `dask worker {scheduler}`, or use --backend local "
                                   f"({type(exc).__name__}: {exc})") from None
        self.address = self.client.scheduler.address

    @property
    def workers(self) -> int:
        return len(self.client.nthreads())

    def describe(self) -> str:
        return f"dask at {self.address} ({self.workers} workers)"

    def scatter(self, obj):
        return self.client.scatter(obj, broadcast=False, hash=False)

    def run(self, fn, tasks, desc=None, unit="task"):
        from distributed import as_completed

        tasks = list(tasks)
        if not tasks:
            return
        name = getattr(fn, "__name__", "task")
        futs = {}
        for key, args in tasks:
            fut = self.client.submit(_on_worker, fn, *args, retries=self.retries, pure=False,
                                     key=f"{name}-{len(futs)}-{os.urandom(6).hex()}")
            futs[fut] = key
        try:
            for fut in progress(as_completed(list(futs)), total=len(futs), desc=desc, unit=unit):
                key = futs[fut]
                if fut.status == "finished":
                    value = fut.result()
                    fut.release()
                    yield Outcome(key, value, None)
                else:
                    try:
                        exc = fut.exception()
                    except Exception as e:  # cancelled futures raise here
                        exc = e
                    yield Outcome(key, None, exc if exc is not None else RuntimeError(f"task {fut.status}"))
        finally:
            self.client.cancel([f for f in futs if not f.done()])

    def close(self):
        if self._own:
            self.client.close()


_MALLOC_TUNED = False


def tune_worker_malloc():
    """Undo the Dask nanny's ``MALLOC_TRIM_THRESHOLD_=65536`` for this worker process (glibc only).

    That setting also fixes glibc's mmap threshold at 128 KiB, so every trial-sized array is a fresh
    ``mmap`` that is page-faulted in and unmapped again, and a sweep task spends several times
    longer in the kernel (``bench_dask.py --workers 1`` shows it). A 32 MiB mmap threshold and a
    256 MiB trim threshold give back the plain process's speed (workers keep up to that much freed
    memory)."""
    global _MALLOC_TUNED
    if _MALLOC_TUNED:
        return
    _MALLOC_TUNED = True
    if "MALLOC_TRIM_THRESHOLD_" not in os.environ or os.environ.get("TOGGLECF_KEEP_MALLOC") == "1":
        return
    try:
        import ctypes

        libc = ctypes.CDLL("libc.so.6")
        libc.mallopt(-3, 32 << 20)   # M_MMAP_THRESHOLD
        libc.mallopt(-1, 256 << 20)  # M_TRIM_THRESHOLD
    except (OSError, AttributeError):  # not glibc
        pass


def _on_worker(fn, *args):
    tune_worker_malloc()
    return fn(*args)


def make_backend(name: str | None = "local", scheduler=None, jobs: int | None = None, retries: int = 2) -> Backend:
    """A backend by name: ``local`` (process pool on ``jobs`` cores) or ``dask`` (``scheduler`` address)."""
    name = (name or "local").lower()
    if name == "local":
        return LocalBackend(jobs)
    if name == "dask":
        return DaskBackend(scheduler, retries=retries)
    raise BackendError(f"unknown backend {name!r}; choose one of {list(BACKENDS)}")


# ------------------------------------------------------------------------------ trials on workers

_CACHE: dict = {}
_CACHE_SIZE = 2


def trial_identity(path) -> str:
    """``name:size:mtime_ns`` of a trial file: results computed on another version of it are not reused."""
    st = Path(path).stat()
    return f"{Path(path).name}:{st.st_size}:{st.st_mtime_ns}"


def data_location(index) -> str | tuple[str, ...]:
    """What a task needs to find ``index``'s trials where it runs (``load_trial_cached``'s ``root``):
    the absolute directory of a ``DatasetIndex``, the tuple of them of a ``MultiIndex``."""
    root = index.root
    if isinstance(root, (tuple, list)):
        return tuple(str(Path(r).resolve()) for r in root)
    return str(Path(root).resolve())


def load_trial_cached(root, name):
    """``open_index(root).load(name)``, keeping the last few trials of this process in memory (a worker
    gets several chunks of the same trial in a row). ``root``: one data directory (``DatasetIndex``,
    plain trial names) or a tuple of them (``MultiIndex``, names ``<dataset>/<trial>``), as given by
    ``data_location``."""
    index = DatasetIndex.from_dir(root) if isinstance(root, (str, os.PathLike)) else open_index(list(root))
    if name not in index.available:
        raise KeyError(f"trial {name} is not present in {root} (as seen from this worker)")
    key = (str(root), name, trial_identity(index.available[name]))
    if key not in _CACHE:
        while len(_CACHE) >= _CACHE_SIZE:
            _CACHE.pop(next(iter(_CACHE)))
        _CACHE[key] = index.load(name)
    return _CACHE[key]


# ------------------------------------------------------------------------------------- CLI glue


def sweep_chunk_size(backend: Backend, chunk_size: int = -1):
    """Grid points per task: ``-1`` (default) one task per trial locally, automatic on Dask;
    ``0`` automatic; ``n`` at most n points per task."""
    if chunk_size is None or chunk_size < 0:
        return 0 if isinstance(backend, DaskBackend) else None
    return int(chunk_size)
