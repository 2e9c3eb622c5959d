"""``togglecf stream``: run a filter live on IMU lines from a serial port, a file or stdin."""
from __future__ import annotations

import argparse
import sys

from togglecf.live.stream import OUTPUT_HEADER, TIME_UNITS, StreamConfig, StreamProcessor, file_chunks, serial_chunks
from togglecf.registry import FILTER_NAMES, TRAINED, FilterSpec

__all__ = ["add_stream_parser"]


def cmd_stream(args):
    if bool(args.port) == bool(args.input):
        raise ValueError("give exactly one of --port DEVICE or --input FILE|-")
    cfg = StreamConfig(fs=args.fs, time_unit=args.time_unit, units=args.units, use_mag=not args.six_d,
                       rate=args.rate, max_gap=args.max_gap, precision=args.precision)
    spec = FilterSpec(args.filter, models=args.models if args.filter in TRAINED else None, use_mag=not args.six_d)
    filt = spec.build(args.fs)
    proc = StreamProcessor(filt, cfg)
    print(OUTPUT_HEADER, flush=True)
    if args.port:
        chunks = serial_chunks(args.port, args.baud, retry_s=args.retry)
        proc.run(chunks)
    elif args.input == "-":
        proc.run(file_chunks(sys.stdin))
    else:
        with open(args.input, "rb") as f:
            proc.run(file_chunks(f))
    return 0


def add_stream_parser(subparsers):
    """``togglecf stream ...`` (wire into ``cli._parser``: ``add_stream_parser(sub)``)."""
    sp = subparsers.add_parser("stream", help="live orientation from a serial IMU (or a CSV file / stdin)",
                               formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    src = sp.add_mutually_exclusive_group(required=True)
    src.add_argument("--port", metavar="DEVICE", help="serial port, e.g. /dev/ttyUSB0 or COM3")
    src.add_argument("--input", metavar="FILE", help="read lines from a file, or - for stdin")
    sp.add_argument("--baud", type=int, default=115200)
    sp.add_argument("--filter", default="madgwick", choices=FILTER_NAMES)
    sp.add_argument("--models", metavar="DIR", help="model directory for --filter toggling")
    sp.add_argument("--units", default="gyr=rad/s,acc=m/s2,mag=uT",
                    help="input units, e.g. gyr=dps,acc=g,mag=uT (gyr: rad/s|dps; acc: m/s2|g|mg; "
                    "mag: uT|nT|G|mG); converted to rad/s, m/s², µT")
    sp.add_argument("--time-unit", choices=sorted(TIME_UNITS), default="s", help="unit of the timestamp t")
    # required: every time constant is converted at this rate, and a wrong guess (BROAD's 285.714 Hz for a
    # 100-Hz sensor) silently scales them all
    sp.add_argument("--fs", type=float, required=True,
                    help="the sensor's nominal sampling rate [Hz] (coefficients, gap detection, first Δt)")
    sp.add_argument("--rate", type=float, default=10.0, help="output lines per second of stream time (0: every sample)")
    sp.add_argument("--6d", dest="six_d", action="store_true", help="lines without magnetometer: t,gx,gy,gz,ax,ay,az")
    sp.add_argument("--max-gap", type=float, default=1.0, help="Δt [s] above which the time base restarts")
    sp.add_argument("--retry", type=float, default=1.0, help="seconds between serial reconnect attempts")
    sp.add_argument("--precision", type=int, default=6, help="decimals printed")
    sp.set_defaults(func=cmd_stream)
    return sp
