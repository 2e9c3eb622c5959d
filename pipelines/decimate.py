"""Write a BROAD-layout copy of a data directory at a lower rate: every ``k`` samples averaged into one.

    python pipelines/decimate.py SRC DST [--factor 3] [--trials LIST]

The IMU signals (``imu_gyr``, ``imu_acc``, ``imu_mag``) are averaged over blocks of ``k`` samples (what a
sensor with a k-times longer output interval and its own averaging delivers); the reference
(``opt_quat``, ``opt_pos``) and ``movement`` are taken at the block's last sample, so the reference is
the orientation at the end of the averaged interval, as the filters report it. ``sampling_rate``
becomes ``fs / k``. ``trials.json`` is copied. Used for the rate check of issue 12 (the same held-out
trials at 95 Hz instead of 285.7 Hz; ``make run`` does it itself: ``togglecf.run.transfer``). Values
outside the whole blocks at the end are dropped.
"""
from __future__ import annotations

import argparse
import sys

from togglecf.data import DatasetIndex
from togglecf.run.transfer import write_decimated


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("src")
    p.add_argument("dst")
    p.add_argument("--factor", type=int, default=3)
    p.add_argument("--trials", default=None)
    args = p.parse_args(argv)
    if args.factor < 2:
        p.error("--factor must be >= 2")
    write_decimated(DatasetIndex.from_dir(args.src), args.dst, args.factor, args.trials, log=print)
    return 0


if __name__ == "__main__":
    sys.exit(main())
