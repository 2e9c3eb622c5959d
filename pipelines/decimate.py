"""Write a BROAD-layout copy of a data directory at a lower rate: every ``k`` samples averaged into one.

    python pipelines/decimate.py SRC DST [--factor 3] [--trials LIST]

The IMU signals (``imu_gyr``, ``imu_acc``, ``imu_mag``) are averaged over blocks of ``k`` samples (what a
sensor with a k-times longer output interval and its own averaging delivers); the reference
(``opt_quat``, ``opt_pos``) and ``movement`` are taken at the block's last sample, so the reference is
the orientation at the end of the averaged interval, as the filters report it. ``sampling_rate``
becomes ``fs / k``. ``trials.json`` is copied. Used for the rate check of issue 12 (the same held-out
trials at 95 Hz instead of 285.7 Hz). Values outside the whole blocks at the end are dropped.
"""
from __future__ import annotations

import argparse
import shutil
import sys
from pathlib import Path

import h5py
import numpy as np

from togglecf.data import DatasetIndex

IMU = ("imu_gyr", "imu_acc", "imu_mag")
AT_END = ("opt_quat", "opt_pos", "movement")


def decimate_trial(trial, factor: int) -> dict:
    """Arrays of one decimated trial (see the module docstring)."""
    n = (trial.n_samples // factor) * factor
    out = {}
    for name, arr in (("imu_gyr", trial.gyr), ("imu_acc", trial.acc), ("imu_mag", trial.mag)):
        out[name] = arr[:n].reshape(-1, factor, 3).mean(axis=1)
    out["opt_quat"] = trial.opt_quat[factor - 1:n:factor]
    if trial.opt_pos is not None:
        out["opt_pos"] = trial.opt_pos[factor - 1:n:factor]
    out["movement"] = np.asarray(trial.movement[factor - 1:n:factor], dtype=np.uint8)
    return out


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("src")
    p.add_argument("dst")
    p.add_argument("--factor", type=int, default=3)
    p.add_argument("--trials", default=None)
    args = p.parse_args(argv)
    if args.factor < 2:
        p.error("--factor must be >= 2")
    index = DatasetIndex.from_dir(args.src)
    dst = Path(args.dst)
    dst.mkdir(parents=True, exist_ok=True)
    shutil.copy(Path(args.src) / "trials.json", dst / "trials.json")
    for name in index.select(args.trials):
        trial = index.load(name)
        arrays = decimate_trial(trial, args.factor)
        with h5py.File(dst / f"{name}.hdf5", "w") as f:
            for k, v in arrays.items():
                f.create_dataset(k, data=v, compression="gzip")
            f.attrs["sampling_rate"] = trial.fs / args.factor
            f.attrs["info"] = f"{name}: every {args.factor} samples averaged (pipelines/decimate.py)"
        print(f"{name}: {trial.n_samples} -> {len(arrays['imu_gyr'])} samples at {trial.fs / args.factor:.3f} Hz")
    return 0


if __name__ == "__main__":
    sys.exit(main())
