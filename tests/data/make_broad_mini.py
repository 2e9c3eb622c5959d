"""Create ``tests/data/broad_mini/`` from the real BROAD trials (see README.md beside this file).

    python tests/data/make_broad_mini.py [BROAD_DIR]      # default: as ``togglecf evaluate`` finds BROAD

The directory is *not* part of the repository (BROAD's files live in ``../shared`` only): the test
suite (``tests/conftest.py``) and the benchmarks' quick modes create it on first use with ``ensure``.

Each mini trial is one contiguous cut ``[start, stop)`` (sample indices of the original trial, at
285.714 Hz) of a real BROAD trial: about 4 s of the rest before the movement starts (the filters
initialise on it, and the labels need rest samples) followed by 10 s of the movement phase. The six
datasets the loader reads (``imu_gyr, imu_acc, imu_mag, opt_quat, opt_pos, movement``) are copied
with their values and dtypes unchanged (float64, ``movement`` bool), gzip-compressed; the file
attributes are BROAD's ``sampling_rate`` (unchanged) and ``info`` (BROAD's text plus one line naming
the cut). ``trials.json`` holds BROAD's 16 groups and the 3 trials' own entries, copied verbatim.
The output is deterministic (no HDF5 timestamps).
"""
from __future__ import annotations

import json
import sys
from pathlib import Path

import h5py
import numpy as np

from togglecf.data.broad import resolve_data_dir

#: trial -> (start, stop): samples of the original file. Movement starts at sample 11449 (02),
#: 7573 (07) and 12802 (24); each cut starts ~4 s before it and is 4000 samples (14.0 s) long.
CUTS = {
    "02_undisturbed_slow_rotation_B": (10300, 14300),
    "07_undisturbed_fast_rotation_B": (6400, 10400),
    "24_disturbed_tapping_A": (11600, 15600),
}
FIELDS = ("imu_gyr", "imu_acc", "imu_mag", "opt_quat", "opt_pos", "movement")
OUT = Path(__file__).resolve().parent / "broad_mini"


def ensure(out: Path = OUT) -> Path:
    """``out`` holding the mini trials, cut from the BROAD directory that ``resolve_data_dir`` finds
    when not there yet (written to a sibling first, then renamed: never half-written). Raises
    ``DataNotFoundError`` when BROAD is nowhere to be found."""
    out = Path(out)
    if (out / "trials.json").is_file():
        return out
    tmp = out.with_name(out.name + ".partial")
    make(resolve_data_dir(), tmp)
    tmp.rename(out)
    return out


def make(src: Path, out: Path = OUT) -> None:
    out.mkdir(parents=True, exist_ok=True)
    index = json.loads((src / "trials.json").read_text())
    mini = {"groups": index["groups"], "trials": {name: index["trials"][name] for name in CUTS}}
    (out / "trials.json").write_text(json.dumps(mini, indent=2, ensure_ascii=False) + "\n")
    for name, (start, stop) in CUTS.items():
        with h5py.File(src / f"{name}.hdf5", "r") as f, h5py.File(out / f"{name}.hdf5", "w", track_order=True) as g:
            n = f["imu_gyr"].shape[0]
            assert 0 <= start < stop <= n, (name, start, stop, n)
            g.attrs["sampling_rate"] = f.attrs["sampling_rate"]
            g.attrs["info"] = (f.attrs["info"] + f"\n\nCut for the togglecf tests: samples {start}:{stop} of the "
                               f"{n} samples of the original trial, values unchanged.")
            for k in FIELDS:
                data = f[k][start:stop]
                g.create_dataset(k, data=data, dtype=f[k].dtype, compression="gzip", compression_opts=9,
                                 track_times=False)
            for k in FIELDS:  # values and dtypes are the original ones
                assert g[k].dtype == f[k].dtype and np.array_equal(g[k][()], f[k][start:stop], equal_nan=k != "movement")
        print(f"{name}: samples {start}:{stop} ({stop - start} samples), {(out / f'{name}.hdf5').stat().st_size} bytes")


if __name__ == "__main__":
    make(Path(sys.argv[1]) if len(sys.argv) > 1 else resolve_data_dir())
