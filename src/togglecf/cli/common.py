"""Command-line options shared by several commands: the execution backend (``--backend``,
``--scheduler``, ``--retries``) and the data directories (``--data``, repeatable), with the one
precedence rule (flags > config ``[run]`` > defaults). Cheap to import (``cli.parsers`` builds every
parser with it)."""
from __future__ import annotations

import sys

from togglecf.core.config import BACKENDS, RUN_DEFAULTS, load_run_section
from togglecf.core.extras import check_extra
from togglecf.data.broad import SELECTION_HELP, open_index
from togglecf.parallel.backend import Backend, BackendError, make_backend

__all__ = ["add_backend_args", "backend_settings", "backend_from_args", "add_data_args", "data_dirs", "data_index",
           "DATA_HELP"]

DATA_HELP = ("data directory in BROAD's layout (trials.json + .hdf5/.mat); repeat for several "
             "(--data A --data B: trial names become <dir name>/<trial>, groups <dir name>/<group> plus one "
             "per directory); default: [run] data of the config, else $TOGGLECF_DATA, else ../shared/data/broad "
             "next to the repo, else ./data/broad")


def add_data_args(sp, trials_help: str = "default: all present"):
    """``--data DIR`` (repeatable) and ``--trials LIST``."""
    sp.add_argument("--data", metavar="DIR", action="append", default=None, help=DATA_HELP)
    sp.add_argument("--trials", metavar="LIST", help=f"{SELECTION_HELP} ({trials_help})")


def data_dirs(args, run_cfg: dict | None = None):
    """The data directories: ``--data`` (all of them) over the config's ``[run] data`` over the default
    location (``None``). For ``tune``/``evaluate`` the config is ``--config``'s."""
    if getattr(args, "data", None):
        return list(args.data)
    if run_cfg is None and getattr(args, "config", None) and getattr(args, "command", "") in ("tune", "evaluate"):
        run_cfg = load_run_section(args.config)
    data = (run_cfg or {}).get("data") or None
    return [data] if isinstance(data, str) else data


#: the ``[run]`` keys that choose the backend
RUN_KEYS = {k: RUN_DEFAULTS[k] for k in ("backend", "scheduler", "retries", "chunk_size")}


def add_backend_args(sp, config: bool = False):
    """``--backend``, ``--scheduler``, ``--retries`` (and ``--config`` for commands without one)."""
    sp.add_argument("--backend", choices=BACKENDS, default=None,
                    help="where the work runs: local (process pool on --jobs cores, default) or dask "
                    "(a dask.distributed cluster at --scheduler); also [run] backend in the config")
    sp.add_argument("--scheduler", metavar="tcp://HOST:8786", default=None,
                    help="Dask scheduler address (start one with `dask scheduler`); also [run] scheduler")
    sp.add_argument("--retries", type=int, default=None, metavar="N",
                    help="Dask: times a failed task is retried (default 2; tasks lost with a worker are "
                    "rescheduled by the scheduler anyway)")
    if config:
        sp.add_argument("--config", metavar="TOML", default=None,
                        help="read [run] backend/scheduler/retries/chunk_size from this config")


def backend_settings(args, run_cfg: dict | None = None) -> dict:
    """Backend settings: command-line flags over the config's ``[run]`` over the defaults."""
    run_cfg = dict(run_cfg or {})
    if run_cfg == {} and getattr(args, "config", None) and getattr(args, "command", "") in ("tune", "evaluate"):
        run_cfg = load_run_section(args.config)
    s = {k: run_cfg.get(k, v) for k, v in RUN_KEYS.items()}
    for k in ("backend", "scheduler", "retries"):
        if getattr(args, k, None) is not None:
            s[k] = getattr(args, k)
    if s["backend"] not in BACKENDS:
        raise BackendError(f"unknown backend {s['backend']!r}; choose one of {list(BACKENDS)}")
    if getattr(args, "scheduler", None) and getattr(args, "backend", None) is None:
        s["backend"] = "dask"  # --scheduler alone on the command line means Dask
    if s["backend"] == "dask":
        check_extra("dask", what="--backend dask")
    return s


def backend_from_args(args, run_cfg: dict | None = None) -> Backend:
    s = backend_settings(args, run_cfg)
    return make_backend(s["backend"], s["scheduler"], getattr(args, "jobs", None), s["retries"])


def data_index(args):
    """The index of ``--data`` (one directory or several) or the config's ``[run] data``; its summary
    on stderr."""
    index = open_index(data_dirs(args))
    print(index.summary(), file=sys.stderr)
    return index
