"""``togglecf stream``: run a filter live on IMU lines from a serial port (the ``stream`` extra), a file
or stdin (no extra). The parser is ``cli.parsers.add_stream_parser``; this module is imported when the
command runs."""
from __future__ import annotations

import sys

from togglecf.cli.parsers import add_stream_parser
from togglecf.core.extras import check_extra
from togglecf.live.stream import OUTPUT_HEADER, StreamConfig, StreamProcessor, file_chunks, serial_chunks
from togglecf.registry import LEARNED_VQF, TRAINED, FilterSpec

__all__ = ["add_stream_parser", "cmd_stream"]


def cmd_stream(args):
    if bool(args.port) == bool(args.input):
        raise ValueError("give exactly one of --port DEVICE or --input FILE|-")
    if args.port:
        check_extra("stream", what="togglecf stream --port")
    cfg = StreamConfig(fs=args.fs, time_unit=args.time_unit, units=args.units, use_mag=not args.six_d,
                       rate=args.rate, max_gap=args.max_gap, precision=args.precision, unit_check_s=args.unit_check)
    spec = FilterSpec(args.filter, models=args.models if args.filter in (*TRAINED, LEARNED_VQF) else None,
                      use_mag=not args.six_d)
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
