"""``togglecf plot euler|error|3d``: orientation figures of one trial (``togglecf.report.plots``). The
parser is ``cli.parsers.add_plot_parser``; this module is imported when the command runs (the ``plot``
extra)."""
from __future__ import annotations

import sys
from pathlib import Path

import matplotlib
import numpy as np

from togglecf.cli.parsers import add_plot_parser
from togglecf.data.broad import open_index
from togglecf.registry import FILTER_NAMES, TOGGLING, TRAINED, FilterSpec
from togglecf.report.plots import animate_3d, animation_path, plot_3d_frames, plot_error, plot_euler

__all__ = ["add_plot_parser", "cmd_plot_euler", "cmd_plot_error", "cmd_plot_3d"]


def _load_trial(args):
    matplotlib.use("Agg")  # the commands only write files
    index = open_index(args.data)
    names = index.select(args.trial)
    if len(names) != 1:
        raise ValueError(f"--trial {args.trial!r} matches {len(names)} trials; give one")
    return index.load(names[0])


def _estimate(trial, name, models, use_mag):
    spec = FilterSpec(name, models=models if name in TRAINED else None, use_mag=use_mag)
    f = spec.build(trial.fs)
    return f.update_batch(trial.gyr, trial.acc, trial.mag if use_mag else None).quat


def _estimates(args, trial) -> dict:
    """name -> quaternions of every filter of ``--filters`` (``--models`` adds toggling)."""
    names = [s.strip() for s in args.filters.split(",") if s.strip()]
    if args.models and TOGGLING not in names:
        names.append(TOGGLING)
    if not names:
        raise ValueError("--filters names no filter")
    bad = [n for n in names if n not in FILTER_NAMES]
    if bad:
        raise ValueError(f"unknown filter {bad[0]!r} in --filters; available: {', '.join(FILTER_NAMES)}")
    trained = [n for n in names if n in TRAINED]
    if trained and not args.models:
        raise ValueError(f"--filters {trained[0]} needs --models DIR (a `togglecf train` model directory)")
    return {n: _estimate(trial, n, args.models, not args.six_d) for n in names}


def _plot_filters(args, figure):
    """``figure(trial, estimates, out=, t_range=)`` of the trial and filters the options name."""
    trial = _load_trial(args)
    t_range = (args.start, args.end if args.end is not None else trial.duration)
    figure(trial, _estimates(args, trial), out=args.out, t_range=t_range)
    print(f"wrote {args.out}", file=sys.stderr)


def cmd_plot_euler(args):
    _plot_filters(args, plot_euler)


def cmd_plot_error(args):
    _plot_filters(args, plot_error)


def cmd_plot_3d(args):
    trial = _load_trial(args)
    q = _estimate(trial, args.filter, args.models, not args.six_d)
    t1 = args.end if args.end is not None else trial.duration
    out = Path(args.out)
    if out.suffix.lower() in (".gif", ".mp4"):
        animate_3d(trial, q, out, fps=args.fps, duration=args.duration, t_range=(args.start, t1), name=args.filter)
        out = animation_path(out)
    else:
        times = np.linspace(args.start, t1 - 1.0 / trial.fs, args.frames)
        plot_3d_frames(trial, q, times, out=out, name=args.filter)
    print(f"wrote {out}", file=sys.stderr)
