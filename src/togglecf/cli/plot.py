"""``togglecf plot euler|error|3d``: orientation figures of one trial (``togglecf.report.plots``)."""
from __future__ import annotations

import sys
from pathlib import Path

import matplotlib
import numpy as np

from togglecf.data.broad import open_index
from togglecf.registry import FILTER_NAMES, TOGGLING, TRAINED, FilterSpec
from togglecf.report.plots import animate_3d, animation_path, plot_3d_frames, plot_error, plot_euler

__all__ = ["add_plot_parser"]


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


def add_plot_parser(subparsers):
    """``togglecf plot euler|error|3d ...`` (wire into ``cli._parser``: ``add_plot_parser(sub)``)."""
    choices = FILTER_NAMES
    p = subparsers.add_parser("plot", help="plot filters' orientation on one trial (Euler angles and their errors, "
                              "BROAD's errors over time, 3-D)")
    psub = p.add_subparsers(dest="plot_kind", required=True)

    def common(sp):
        sp.add_argument("--trial", required=True, help="one trial number or name, e.g. 05")
        sp.add_argument("--data", metavar="DIR", help="BROAD directory (default: as `togglecf evaluate`)")
        sp.add_argument("--models", metavar="DIR", help="model directory for the toggling filter")
        sp.add_argument("--6d", dest="six_d", action="store_true", help="ignore the magnetometer")
        sp.add_argument("--start", type=float, default=0.0, help="start time [s]")
        sp.add_argument("--end", type=float, default=None, help="end time [s] (default: trial end)")
        sp.add_argument("--out", required=True, metavar="FILE")

    sp = psub.add_parser("euler", help="roll/pitch/yaw of estimates vs ground truth, and estimate − truth per "
                         "angle (wrapped to ±180°) -> PNG/SVG")
    common(sp)
    sp.add_argument("--filters", default="madgwick", help="comma-separated filter names (default: madgwick); "
                    f"any of {', '.join(choices)}; --models adds toggling")
    sp.set_defaults(func=cmd_plot_euler)

    sp = psub.add_parser("error", help="BROAD's total/heading/inclination error over time of several filters "
                         "-> PNG/SVG")
    common(sp)
    sp.add_argument("--filters", default="madgwick,vqf_core", help="comma-separated filter names (default: "
                    f"madgwick,vqf_core); any of {', '.join(choices)}; --models adds toggling")
    sp.set_defaults(func=cmd_plot_error)

    sp = psub.add_parser("3d", help="IMU box of an estimate beside the truth: .gif/.mp4 animation or .png frames")
    common(sp)
    sp.add_argument("--filter", default="madgwick", choices=choices)
    sp.add_argument("--fps", type=int, default=10)
    sp.add_argument("--duration", type=float, default=None, help="animation length [s] (default: min(8, span); "
                    "the trial or --start/--end span is subsampled to fps*duration frames)")
    sp.add_argument("--frames", type=int, default=8, help="number of key frames for a still image")
    sp.set_defaults(func=cmd_plot_3d)
    return p
