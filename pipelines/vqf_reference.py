"""VQF's BROAD errors on the trials present (the reference our filters are compared with).

    .venv/bin/python pipelines/vqf_reference.py [--data DIR]

Runs ``vqf.VQF(Ts).updateBatch(gyr, acc, mag)`` (default parameters, 9D output ``quat9D``, ENU)
on every trial and prints the mean total/heading/inclination RMSE [deg] with the project's
own metrics (``togglecf.metrics.broad.trial_errors``), plus the 6D inclination.
"""
from __future__ import annotations

import argparse

import numpy as np
import vqf

from togglecf.data.broad import DatasetIndex, resolve_data_dir
from togglecf.metrics.broad import trial_errors


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--data", default=None)
    args = p.parse_args(argv)
    index = DatasetIndex.from_dir(resolve_data_dir(args.data))
    rows = []
    for name in index.select(None):
        t = index.load(name)
        out = vqf.VQF(1.0 / t.fs).updateBatch(np.ascontiguousarray(t.gyr), np.ascontiguousarray(t.acc),
                                              np.ascontiguousarray(t.mag))
        e9 = trial_errors(out["quat9D"], t.opt_quat, t.movement)
        e6 = trial_errors(out["quat6D"], t.opt_quat, t.movement, six_d=True)
        rows.append((e9["total"], e9["heading"], e9["inclination"], e6["total"]))
        print(f"{name:45s} total {e9['total']:7.3f} heading {e9['heading']:7.3f} incl {e9['inclination']:6.3f}"
              f"   6D total {e6['total']:7.3f}")
    m = np.mean(rows, axis=0)
    print(f"\nVQF mean over {len(rows)} trials: 9D total {m[0]:.3f}°, heading {m[1]:.3f}°, inclination {m[2]:.3f}°;"
          f" 6D total (heading offset removed) {m[3]:.3f}°")


if __name__ == "__main__":
    main()
