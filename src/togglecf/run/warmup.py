"""Compile the kernels of the learned filters ahead, so that the workers of a pool load them instead.

numba compiles a kernel in the first process that calls it and keeps it in its on-disk cache
(``NUMBA_CACHE_DIR``, keyed on the package's source): on a fresh machine every worker of a pool would
otherwise compile the same kernels at the start of its first task, at the same time, for about a
minute and a half of its time. ``make run`` starts one process per family of ``FAMILIES`` at its
start, while the classic filters' grids run (``start_compiling``), and waits for them before its pool
starts (``Compiling.wait``). What a family runs is the learned filters' own code on a few seconds of
made-up samples, with the shipped pretrained model's trees in the loop: the types are those of the
tasks, so the cache holds what they call; the two biggest classic filters come first, compiled for the
grids that run last. A failure is logged and costs nothing but the time: the tasks compile what they
miss.

    python -m togglecf.run.warmup toggling|vqf
"""
from __future__ import annotations

import logging
import subprocess
import sys
import tempfile

import numpy as np

from togglecf.filters.toggling import TogglingFilter
from togglecf.filters.vqf_toggling import VQFTogglingFilter
from togglecf.registry import FilterSpec
from togglecf.run.scoring import warm_up
from togglecf.toggling.gains import GainSearch, VQFGainSearch
from togglecf.toggling.inloop import ModelTogglingFilter, ModelVQFTogglingFilter
from togglecf.toggling.pretrained import load_pretrained

__all__ = ["FAMILIES", "compile_kernels", "start_compiling", "Compiling"]

log = logging.getLogger(__name__)

#: family -> (the prediction-driven filter, its model-in-the-loop twin, the search whose start it runs, the
#: classic filters whose grids come last in the study: compiled first, the study's process loads them)
FAMILIES = {"toggling": (TogglingFilter, ModelTogglingFilter, GainSearch, ("vqf_core", "ekf")),
            "vqf": (VQFTogglingFilter, ModelVQFTogglingFilter, VQFGainSearch, ())}

_RATE_HZ = 100.0
_SECONDS = 20.0  # longer than a feature window, so the trees run in the loop


def _samples(n: int, rng) -> tuple:
    """Made-up IMU samples ``(N, 3)`` each: slow rotation, gravity, a 40 µT field (rad/s, m/s², µT)."""
    gyr = 0.2 * rng.standard_normal((n, 3))
    acc = np.array([0.0, 0.0, 9.81]) + 0.5 * rng.standard_normal((n, 3))
    mag = np.array([20.0, 0.0, -35.0]) + rng.standard_normal((n, 3))
    return gyr, acc, mag


def compile_kernels(family: str) -> None:
    """Run the filters of ``family`` (a key of ``FAMILIES``): its classic filters as a grid does
    (``run.scoring.warm_up``), then its learned filter in 9D and 6D, with predictions given and with
    the pretrained model's trees in the loop, and the trees' batch prediction: each kernel is compiled,
    or loaded from the cache."""
    batch_filter, in_loop_filter, search, classic = FAMILIES[family]
    for name in classic:
        warm_up(FilterSpec(name))
    models = load_pretrained().models
    rng = np.random.default_rng(0)
    n = int(_SECONDS * _RATE_HZ)
    gyr, acc, mag = _samples(n, rng)
    settings = search().start(models.class_names, models.static_state)
    n_states = len(models.class_names)
    pred = np.hstack([rng.dirichlet(np.ones(n_states), n), 0.1 * rng.standard_normal((n, 6))])
    for use_mag in (True, False):
        m = mag if use_mag else None
        batch_filter(_RATE_HZ, settings, use_mag=use_mag).update_batch(gyr, acc, m, predictions=pred)
        in_loop_filter(_RATE_HZ, settings, models=models, use_mag=use_mag).update_batch(gyr, acc, m)
    models.predict_samples(gyr, acc, mag, _RATE_HZ)


class Compiling:
    """The processes ``start_compiling`` started; ``wait`` for them (a failed one is logged)."""

    def __init__(self, procs: dict):
        self.procs = procs  # family -> (process, its stderr: a temporary file)

    def wait(self) -> None:
        for family, (proc, err) in self.procs.items():
            if proc.wait() != 0:
                err.seek(0)
                last = err.read().decode(errors="replace").strip().splitlines()[-1:] or ["no message"]
                log.warning(f"compiling the {family} kernels ahead failed ({last[0]}): the tasks compile them")
            err.close()


def start_compiling(families=tuple(FAMILIES)) -> Compiling:
    """One process per family (``python -m togglecf.run.warmup FAMILY``), started and not waited for: a
    fresh interpreter each, so this process keeps no thread and no child that a later fork would copy."""
    procs = {}
    for f in families:
        err = tempfile.TemporaryFile()  # a file, not a pipe: a chatty child never blocks on a full pipe
        procs[f] = (subprocess.Popen([sys.executable, "-m", "togglecf.run.warmup", f], stdout=subprocess.DEVNULL,
                                     stderr=err), err)
    return Compiling(procs)


def main(argv=None) -> int:
    args = sys.argv[1:] if argv is None else argv
    if len(args) != 1 or args[0] not in FAMILIES:
        print(f"usage: python -m togglecf.run.warmup {'|'.join(FAMILIES)}", file=sys.stderr)
        return 2
    compile_kernels(args[0])
    return 0


if __name__ == "__main__":
    sys.exit(main())
