"""Speed of the toggling CF with its models inside the compiled loop, against VQF's C++ batch
update, measured in the same run on the same BROAD trial (best of --repeats, after warm-up).

    python pipelines/bench_toggling.py [--models models/default] [--trial 05] [--repeats 5]

Needs a trained model directory (`togglecf train --out models/default`) and the dev extra `vqf`.
"""
import argparse
import sys
import time

import numpy as np

from togglecf.data.broad import DatasetIndex, resolve_data_dir
from togglecf.filters import ComplementaryFilter
from togglecf.filters.toggling import TogglingFilter
from togglecf.toggling import load_toggling_filter


def best_time(run, repeats):
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        run()
        times.append(time.perf_counter() - t0)
    return min(times)


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--models", default="models/default")
    p.add_argument("--data", metavar="DIR")
    p.add_argument("--trial", default="05")
    p.add_argument("--repeats", type=int, default=5)
    args = p.parse_args(argv)
    try:
        from vqf import VQF
    except ImportError:
        sys.exit("bench_toggling needs the reference package vqf: pip install -e '.[dev]'")
    index = DatasetIndex.from_dir(resolve_data_dir(args.data))
    t = index.load(index.select(args.trial)[0])
    try:
        probe = load_toggling_filter(args.models, t.fs)
    except FileNotFoundError as exc:
        sys.exit(f"{exc}\nTrain the models first: togglecf train --out {args.models}")
    gyr, acc, mag = (np.ascontiguousarray(x) for x in (t.gyr, t.acc, t.mag))
    n = t.n_samples
    probe.update_batch(gyr[:100], acc[:100], mag[:100])  # compile
    preds = probe.models.predict_samples(gyr, acc, mag, t.fs)
    TogglingFilter(t.fs, probe.settings).update_batch(gyr[:10], acc[:10], mag[:10], predictions=preds[:10])
    ComplementaryFilter(t.fs).update_batch(gyr[:10], acc[:10], mag[:10])
    runs = {
        "vqf (C++ updateBatch)": lambda: VQF(1.0 / t.fs).updateBatch(gyr, acc, mag),
        "toggling, models in the loop": lambda: load_toggling_filter(args.models, t.fs).update_batch(gyr, acc, mag),
        "toggling core, predictions given": lambda: TogglingFilter(t.fs, probe.settings).update_batch(
            gyr, acc, mag, predictions=preds),
        "fixed-gain cf": lambda: ComplementaryFilter(t.fs).update_batch(gyr, acc, mag),
    }
    us = {k: 1e6 * best_time(f, args.repeats) / n for k, f in runs.items()}
    ref = us["vqf (C++ updateBatch)"]
    f = probe.models.forest
    print(f"trial {t.name}: {n} samples; models: {len(f.roots)} trees ({len(probe._forest.roots)} walked: outputs "
          f"with zero noise weight are skipped), {f.n_nodes} nodes, a prediction every {probe.hop} samples; "
          f"best of {args.repeats}")
    print(f"{'filter':36s} {'µs/sample':>10s} {'÷ VQF':>7s}")
    for k, v in us.items():
        print(f"{k:36s} {v:10.3f} {v / ref:7.2f}")
    ratio = us["toggling, models in the loop"] / ref
    print(f"\ngoal: toggling with in-loop inference <= 2x VQF -> {ratio:.2f}x ({'met' if ratio <= 2 else 'NOT met'})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
