"""Speed of the toggling CF with its models inside the compiled loop, against VQF's C++ batch
update, measured in the same run on the same BROAD trial (best of --repeats, interleaved, after warm-up).

    python pipelines/bench_toggling.py [--quick] [--models models/default] [--trial 05] [--repeats 5] [--out PATH]

Needs a trained model directory (`togglecf train --out models/default`) and the dev extra `vqf`.
Full run: table in ``reports/bench/bench_toggling.md``/``.csv``. ``--quick`` (without
``--models``): tiny models (15 + 10 trees of depth 4, default gains) trained in seconds on the
mini data (``tests/data/broad_mini``, or ``synthetic_mini`` without BROAD), timed on its trial 24 (4000 samples), 2 repeats.
"""
from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

import numpy as np
from bench_common import add_common_args, best_interleaved, context_note, data_dir, finish, vqf_batch

from togglecf.data.broad import DatasetIndex, resolve_data_dir
from togglecf.filters import ComplementaryFilter
from togglecf.filters.toggling import TogglingFilter
from togglecf.run.config import load_config
from togglecf.run.train import run_training
from togglecf.filters import VQFCoreFilter
from togglecf.filters.vqf_toggling import VQFTogglingFilter
from togglecf.registry import VQF_TOGGLING
from togglecf.toggling import ModelTogglingFilter, load_compiled_models, load_toggling_filter
from togglecf.toggling.inloop import ModelVQFTogglingFilter

NAME = "bench_toggling"
QUICK_TRIAL = "24"


def tiny_models(data, out) -> Path:
    """15 + 10 trees of depth 4 on the mini trials, no CV, no gains (as the tests' fixture)."""
    cfg = load_config()
    cfg["classifier"].update(n_estimators=15, max_depth=4)
    cfg["regressor"].update(n_estimators=10, max_depth=4)
    cfg["gains"]["learn"] = False
    run_training(cfg, data_dir=data, trials="02,07,24", out=out, cv=False, verbose=False)
    return Path(out)


def make_filter(models, fs):
    """The trained filter (learned 9D gains); a model directory without gains.json runs with fixed
    illustrative gains, one per state from τ 0.17 s (rest) up (said in the output): speed does not
    depend on the gains' values, only on which outputs the filter uses."""
    if (Path(models) / "gains.json").is_file():
        return load_toggling_filter(models, fs), "learned gains"
    compiled = load_compiled_models(models)
    k = len(compiled.class_names)
    return (ModelTogglingFilter(fs, models=compiled, tau_acc=tuple(np.geomspace(0.1732, 17.5, k)),
                                tau_mag=tuple(np.geomspace(0.6982, 35.0, k)), output_tau=0.002907),
            "fixed gains (no gains.json)")


def make_vqf_filter(models, fs):
    """The VQF core with learned time constants (``vqf_9d`` gains when stored, else the core's own
    values for every state: the same work per sample, learning off)."""
    try:
        return load_toggling_filter(models, fs, kind=VQF_TOGGLING)
    except KeyError:  # no vqf_9d gains in gains.json
        return ModelVQFTogglingFilter(fs, models=load_compiled_models(models))
    except FileNotFoundError:
        return ModelVQFTogglingFilter(fs, models=load_compiled_models(models))


def main(argv=None) -> dict:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_common_args(p, NAME)
    p.add_argument("--models", default=None, help="model directory (default models/default; --quick: tiny models "
                   "trained on the mini data)")
    p.add_argument("--trial", default=None, help=f"default 05; --quick {QUICK_TRIAL}")
    p.add_argument("--repeats", type=int, default=None, help="default 5; --quick 2")
    args = p.parse_args(argv)
    try:
        import vqf  # noqa: F401
    except ImportError:
        sys.exit("bench_toggling needs the reference package vqf: pip install -e '.[dev]'")
    index = DatasetIndex.from_dir(resolve_data_dir(data_dir(args)))
    t = index.load(index.select(args.trial or (QUICK_TRIAL if args.quick else "05"))[0])
    repeats = args.repeats or (2 if args.quick else 5)
    with tempfile.TemporaryDirectory() as tmp:
        models = args.models
        if models is None:
            models = tiny_models(index.root, Path(tmp) / "tiny") if args.quick else "models/default"
        try:
            probe, gains = make_filter(models, t.fs)
        except FileNotFoundError as exc:
            sys.exit(f"{exc}\nTrain the models first: togglecf train --out {models}")
        gyr, acc, mag = (np.ascontiguousarray(x) for x in (t.gyr, t.acc, t.mag))
        n = t.n_samples
        preds = probe.models.predict_samples(gyr, acc, mag, t.fs)
        vqf_probe = make_vqf_filter(models, t.fs)
        runs = {
            "vqf (VQF.updateBatch, C++)": vqf_batch(t.fs, gyr, acc, mag),
            "toggling, models in the loop": lambda: (probe.reset(), probe.update_batch(gyr, acc, mag)),
            "toggling core, predictions given": lambda: TogglingFilter(t.fs, probe.settings).update_batch(
                gyr, acc, mag, predictions=preds),
            "fixed-gain cf": lambda: ComplementaryFilter(t.fs).update_batch(gyr, acc, mag),
            "vqf_toggling (VQF core + learned τ), models in the loop": lambda: (vqf_probe.reset(),
                                                                               vqf_probe.update_batch(gyr, acc, mag)),
            "vqf_toggling core, predictions given": lambda: VQFTogglingFilter(t.fs, vqf_probe.settings).update_batch(
                gyr, acc, mag, predictions=preds),
            "vqf_core alone (learning off)": lambda: VQFCoreFilter(t.fs).update_batch(gyr, acc, mag),
        }
        us = {k: 1e6 * v / n for k, v in best_interleaved(runs, repeats).items()}
    ref = us["vqf (VQF.updateBatch, C++)"]
    f = probe.models.forest
    what = (f"Trial {t.name} ({n} samples at {t.fs:.1f} Hz), 9D, {gains}; models: {len(f.roots)} trees "
            f"({len(probe.forest.roots)} walked: outputs with zero noise weight are skipped), {f.n_nodes} nodes, a "
            f"prediction every {probe.hop} samples; best of {repeats} interleaved runs after a warm-up")
    print(what)
    rows = [{"filter": k, "us_per_sample": v, "ratio_to_vqf": v / ref} for k, v in us.items()]
    ratios = {k: v / ref for k, v in us.items()}
    res = finish(NAME, args, rows, ["filter", "us_per_sample", "ratio_to_vqf"], "Toggling CF speed against VQF",
                 [context_note(what, args)], ratios=ratios)
    ratio = ratios["toggling, models in the loop"]
    print(f"\ngoal: toggling with in-loop inference <= 2x VQF -> {ratio:.2f}x ({'met' if ratio <= 2 else 'NOT met'})")
    vr = ratios["vqf_toggling (VQF core + learned τ), models in the loop"]
    core = ratios["vqf_core alone (learning off)"]
    print(f"goal (issue 13): vqf_toggling with models in the loop <= 1.5x VQF -> {vr:.2f}x "
          f"({'met' if vr <= 1.5 else 'NOT met'}); core alone <= 1x -> {core:.2f}x ({'met' if core <= 1.0 else 'NOT met'})")
    return res


if __name__ == "__main__":
    main()
