"""``togglecf plot euler|error|3d``: orientation figures of one trial (``togglecf.report.plots``). The
parser is ``cli.parsers.add_plot_parser``; this module is imported when the command runs (the ``plot``
extra)."""
from __future__ import annotations

import sys
from pathlib import Path

import matplotlib
import numpy as np

from togglecf.cli.filter_list import filter_names, filter_specs
from togglecf.cli.parsers import add_plot_parser
from togglecf.cli.common import data_dirs
from togglecf.data.broad import open_index
from togglecf.registry import LEARNED_VQF, TOGGLING, TRAINED, FilterSpec, is_portable_file
from togglecf.report.plots import animate_3d, animation_path, plot_3d_frames, plot_error, plot_euler

__all__ = ["add_plot_parser", "cmd_plot_euler", "cmd_plot_error", "cmd_plot_3d"]


def _load_trial(args):
    matplotlib.use("Agg")  # the commands only write files
    index = open_index(data_dirs(args))  # one --data directory or several, as evaluate
    names = index.select(args.trial)
    if len(names) != 1:
        shown = f" ({', '.join(names[:4])}{', ...' if len(names) > 4 else ''})" if names else ""
        raise ValueError(f"--trial {args.trial!r} matches {len(names)} trials{shown}; give one"
                         + (" as <dir name>/<trial>" if len(names) > 1 else ""))
    return index.load(names[0])


def _estimate(trial, spec: FilterSpec):
    return spec.build(trial.fs).update_batch(trial.gyr, trial.acc, trial.mag if spec.use_mag else None).quat


def _estimates(args, trial) -> dict:
    """name -> quaternions of every filter of ``--filters`` (``--models`` adds toggling)."""
    names = filter_names(args.filters)
    if args.models and not is_portable_file(args.models) and TOGGLING not in names:
        names.append(TOGGLING)
    return {s.name: _estimate(trial, s) for s in filter_specs(names, args.models, use_mag=not args.six_d)}


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
    spec = FilterSpec(args.filter, models=args.models if args.filter in (*TRAINED, LEARNED_VQF) else None,
                      use_mag=not args.six_d)
    q = _estimate(trial, spec)
    t1 = args.end if args.end is not None else trial.duration
    out = Path(args.out)
    if out.suffix.lower() in (".gif", ".mp4"):
        animate_3d(trial, q, out, fps=args.fps, duration=args.duration, t_range=(args.start, t1), name=args.filter)
        out = animation_path(out)
    else:
        times = np.linspace(args.start, t1 - 1.0 / trial.fs, args.frames)
        plot_3d_frames(trial, q, times, out=out, name=args.filter)
    print(f"wrote {out}", file=sys.stderr)
