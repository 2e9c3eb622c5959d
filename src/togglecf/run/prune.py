"""Pruning sweep: model size against the toggling filter's held-out BROAD error.

A sweep point is a model size: trees per booster and tree depth (classifier, regressors) and the
number of features the trees may use (``[run] max_features``, the most important by gain on
the same training rows). Every point is judged by what a user deploys, the *toggling filter*
with those models, under the study's protocol (``study.trial_folds``): per fold, on the
training trials only, ``run_training`` fits the models (inner CV for out-of-fold predictions,
then the gains learned on them, 9D); the fold's test trials are then filtered with the models in
the loop (``ModelTogglingFilter``) and scored with BROAD's total RMSE. Every trial is tested once:
the point's error is the mean over all trials of models that never saw them.

Sizes are of the trees the filter walks (outputs with a learned noise weight of 0 are dropped):

* ``array_*``: the merged forest in the compact array format (``export.forest_to_c``), object
  code of ``gcc -Os -c`` for the host and rv32imc (the ESP32-C3's ISA); the largest over the
  folds' models (conservative);
* ``tl2cgen_*`` / ``tl2cgen_q_*``: TL2cgen's if/else code (plain / quantized thresholds) of the
  same boosters, summed over them, from fold 0's models (it is slower to generate);
* ``ram_bytes``: rv32imc stack of ``tcf_predict`` (``-fstack-usage``) plus the float32 feature
  row and outputs it reads and writes;
* ``us_per_prediction``: host time of the array walker per window (gcc -O2), test windows.

The reference point (``reference=True``) is the model's own config, unpruned; it is measured by
the same code, so "worse than unpruned" compares like with like. Rows are appended to
``sweep_rows.jsonl`` as points finish, so an interrupted sweep resumes with the missing points.
"""
from __future__ import annotations

import hashlib
import itertools
import json
import logging
import shutil
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from togglecf.core.extras import require
from togglecf.core.io import atomic_write_bytes, atomic_write_text
from togglecf.data.broad import open_index
from togglecf.embedded.forest_export import bundle_boosters
from togglecf.embedded.measure import array_measurements, tl2cgen_sizes, used_boosters, used_features
from togglecf.embedded.toolchain import RISCV_GCC
from togglecf.features.windows import FeatureSettings
from togglecf.learn.dataset import build_dataset
from togglecf.learn.folds import trial_folds
from togglecf.learn.labels import LabelSettings
from togglecf.learn.models import load_bundle
from togglecf.parallel.backend import InlineBackend, data_location, load_trial_cached
from togglecf.registry import TOGGLING, FilterSpec
from togglecf.report.study_report import paired_test, png_bytes
from togglecf.run.config import load_config
from togglecf.run.scoring import score_trials
from togglecf.run.sweep import ResultStore
from togglecf.run.train import run_training
from togglecf.toggling.load import load_toggling_filter

__all__ = ["PrunePoint", "default_points", "pruning_sweep", "existing_sweep_rows", "pareto_front", "choose_point", "tie_verdicts",
           "write_sweep_report", "format_front", "SIZE_KEYS", "DEFAULT_EXPORT_POINT", "DEFAULT_EXPORT_SIZES"]

SIZE_KEYS = {"array": "array_riscv_bytes", "tl2cgen": "tl2cgen_riscv_bytes"}
HOST_SIZE_KEYS = {"array": "array_host_bytes", "tl2cgen": "tl2cgen_host_bytes"}


@dataclass(frozen=True)
class PrunePoint:
    """Model size of one sweep point (``max_features`` 0: all features)."""

    clf_trees: int
    clf_depth: int
    reg_trees: int
    reg_depth: int
    max_features: int = 0
    reference: bool = False

    @property
    def key(self) -> str:
        f = "all" if not self.max_features else str(self.max_features)
        return f"c{self.clf_trees}x{self.clf_depth}_r{self.reg_trees}x{self.reg_depth}_f{f}"

    def apply(self, cfg: dict) -> dict:
        """A copy of the training config ``cfg`` with this point's model sizes."""
        out = {s: dict(v) for s, v in cfg.items()}
        out["classifier"].update(n_estimators=self.clf_trees, max_depth=self.clf_depth)
        out["regressor"].update(n_estimators=self.reg_trees, max_depth=self.reg_depth)
        out["run"]["max_features"] = int(self.max_features)
        return out

    @classmethod
    def of_config(cls, cfg: dict, reference: bool = True) -> "PrunePoint":
        return cls(int(cfg["classifier"].get("n_estimators", 60)), int(cfg["classifier"].get("max_depth", 5)),
                   int(cfg["regressor"].get("n_estimators", 40)), int(cfg["regressor"].get("max_depth", 4)),
                   int(cfg["run"].get("max_features", 0) or 0), reference)


#: The pruned point ``togglecf export --max-bytes N`` uses when no sweep exists: 10 trees of depth 4
#: per booster (classifier and regressors), all features. Why: the pruning sweep of ``models/default``
#: (25 BROAD trials, 5 held-out folds, inner 3-fold CV; ``togglecf prune``) chose it for
#: ``--max-bytes 32768`` (the lowest held-out error within that budget) on an earlier feature set; on
#: the current features the sweep (``docs/results/sweep.md``) picks 30 trees of depth 3 for the
#: toggling CF, but the learned VQF filter's 9D C export (trees + VQF core in soft float) fits 32 KiB
#: with this point only just, so it stays the default. It is not re-chosen per model: ``--full-sweep``
#: does that.
DEFAULT_EXPORT_POINT = PrunePoint(10, 4, 10, 4, 0)

#: The default point's sizes [bytes] measured in the pruning sweep of ``docs/results/sweep.md``
#: of the models trained on all 25 BROAD trials with the default config (``pipelines/main.py --full``'s
#: ``build/transfer/models_broad``; rv32imc ``-Os`` and host): a budget below them cannot be met
#: without a sweep.
DEFAULT_EXPORT_SIZES = {"array_riscv_bytes": 17704, "tl2cgen_riscv_bytes": 59770,
                        "array_host_bytes": 17845, "tl2cgen_host_bytes": 53690}


def default_points(cfg: dict, trees=(10, 20, 30), depths=(3, 4), features=(0, 24, 12)) -> list:
    """The reference (``cfg``'s own sizes) then every (trees, depth, features) combination,
    applied alike to the classifier and the regressors."""
    ref = PrunePoint.of_config(cfg)
    pts = [ref] + [PrunePoint(n, d, n, d, f) for n, d, f in itertools.product(trees, depths, features)]
    unique = {}
    for p in pts:  # a grid point equal to the reference is run once, as the reference
        unique.setdefault(p.key, p)
    return list(unique.values())


log = logging.getLogger(__name__)


# ------------------------------------------------------------------------------ measurements


# ------------------------------------------------------------------------------------- sweep

def _sweep_identity(cfg, names, folds, inner_folds, data_files) -> str:
    blob = json.dumps({"cfg": {k: v for k, v in cfg.items() if k != "run"}, "seed": cfg["run"]["seed"],
                       "trials": names, "folds": folds, "inner": inner_folds, "files": data_files},
                      sort_keys=True, default=str)
    return hashlib.sha256(blob.encode()).hexdigest()[:16]


def _sweep_fold(cfg, data, root, names, test, fold_dir, riscv: bool, tl2cgen: bool):
    """One (point, fold) of the sweep (a backend task): train on the fold's training trials, filter
    its test trials with the models in the loop, measure the trees the filter walks."""
    t0 = time.perf_counter()
    train = [n for n in names if n not in test]
    run_training(cfg, data_dir=root, trials=",".join(train), out=fold_dir, cv=True, verbose=False, dataset=data,
                 backend=InlineBackend())
    trials = [load_trial_cached(root, n) for n in test]
    per_trial = [{"trial": r.trial, **r.errors} for r, _ in score_trials(trials, FilterSpec(TOGGLING, models=fold_dir))]
    f = load_toggling_filter(fold_dir, trials[-1].fs)  # the trees this filter walks, as deployed
    k = len(f.models.class_names)
    sizes = array_measurements(f.forest, k, data.subset(test).X, riscv)
    tl = {}
    if tl2cgen:
        used = used_boosters(f.forest, k)
        tl = tl2cgen_sizes({n: b for n, b in bundle_boosters(load_bundle(fold_dir)).items() if n in used}, riscv)
    return per_trial, sizes, used_features(f.forest), tl, time.perf_counter() - t0


def _point_row(p: "PrunePoint", folds: list) -> tuple:
    """A point's sweep row and per-trial errors from its folds' ``_sweep_fold`` results (in fold
    order): errors over all test trials; sizes the largest over the folds' models; TL2cgen sizes
    from fold 0; time per prediction the median; ``seconds`` the summed compute time."""
    per_trial = [{**r, "fold": k} for k, f in enumerate(folds) for r in f[0]]
    sizes = [f[1] for f in folds]
    tot = np.array([r["total"] for r in per_trial])

    def largest(name):
        vals = [s[name] for s in sizes if s[name] is not None]
        return max(vals) if vals else None

    row = {"key": p.key, **asdict(p), "features_used": max(f[2] for f in folds),
           "mean_total": float(tot.mean()), "mean_heading": float(np.mean([r["heading"] for r in per_trial])),
           "mean_inclination": float(np.mean([r["inclination"] for r in per_trial])), "max_total": float(tot.max()),
           "array_host_bytes": largest("array_host_bytes"), "array_riscv_bytes": largest("array_riscv_bytes"),
           "ram_bytes": largest("ram_bytes"), "us_per_prediction": float(np.median([s["us_per_prediction"] for s in sizes])),
           **folds[0][3], "seconds": float(sum(f[4] for f in folds)),
           "trial_totals": {r["trial"]: float(r["total"]) for r in per_trial}}
    return row, per_trial


def pruning_sweep(model_dir, out_dir, points=None, folds: int = 5, inner_folds: int = 3, data_dir=None,
                  riscv: bool = True, log=log.info, backend=None) -> list:
    """Run (or resume) the sweep of ``points`` (default ``default_points``) for the model
    directory ``model_dir``: its config, training trials and gain search, only the model sizes
    change. Writes ``out_dir/sweep_rows.jsonl`` (one line per finished point, with per-trial
    errors) and returns the rows (dicts, see the module docstring), in ``points`` order.

    Points already in the journal for the same config, trials, folds and data files are not
    computed again. ``backend`` (``togglecf.parallel.backend``; default: this process, point after point): every (point,
    fold) is one task; on Dask the window data is scattered once, the trials are loaded on the
    workers, and ``out_dir`` must be on a file system the workers share (each task writes its
    fold's model directory there). Results do not depend on where the tasks ran."""
    riscv = riscv and shutil.which(RISCV_GCC) is not None
    cfg0, index, names, identity = _sweep_setup(model_dir, data_dir, folds, inner_folds)
    points = list(points or default_points(cfg0))
    out = Path(out_dir).resolve()
    out.mkdir(parents=True, exist_ok=True)
    rows_path = out / "sweep_rows.jsonl"
    test_sets = trial_folds(names, folds)
    backend = backend or InlineBackend()
    key = lambda p: f"{identity}/{p.key}"  # noqa: E731  (a point of this very sweep)
    with ResultStore(rows_path, required=("row", "per_trial")) as store:
        todo = [p for p in points if key(p) not in store.done]
        log(f"pruning sweep of {model_dir}: {len(points)} points x {len(test_sets)} folds on {len(names)} trials "
            f"({len(points) - len(todo)} already done in {store.path}) on {backend.describe()}")
        if not todo:
            return [store.done[key(p)]["row"] for p in points]
        t0 = time.perf_counter()
        label_settings = LabelSettings.from_dict({**cfg0["labels"], "seed": cfg0["run"]["seed"]})
        data = build_dataset(index, names, label_settings, FeatureSettings.from_dict(cfg0["features"]),
                             ransac=label_settings.ransac, backend=backend)
        log(f"dataset built once in {time.perf_counter() - t0:.0f} s")
        handle = backend.scatter(data)
        where = data_location(index)
        tasks = [((i, k), (p.apply(cfg0), handle, where, names, test, str(out / "runs" / p.key / f"fold{k}"),
                           riscv, k == 0))
                 for i, p in enumerate(todo) for k, test in enumerate(test_sets)]
        parts = {i: {} for i in range(len(todo))}
        n_done = 0
        for o in backend.run(_sweep_fold, tasks, desc="pruning sweep", unit="fold"):
            if o.error is not None:
                raise o.error
            i, k = o.key
            parts[i][k] = o.value
            if len(parts[i]) < len(test_sets):
                continue
            p = todo[i]
            row, per_trial = _point_row(p, [parts[i][k] for k in range(len(test_sets))])
            store.write([{"key": key(p), "row": row, "per_trial": per_trial}])  # one line per point, fsynced
            n_done += 1
            log(f"[{n_done}/{len(todo)}] {p.key}: mean total {row['mean_total']:.3f}°, "
                f"rv32 array {_kib(row['array_riscv_bytes'])}, tl2cgen {_kib(row.get('tl2cgen_riscv_bytes'))} "
                f"({row['seconds']:.0f} s)")
        return [store.done[key(p)]["row"] for p in points]


def _sweep_setup(model_dir, data_dir, folds, inner_folds):
    """The sweep's training config, data index, trials and identity (the journal's key prefix)."""
    bundle = load_bundle(model_dir)
    cfg0 = load_config(bundle.metadata["config"])
    cfg0["gains"].update(learn=True, modes=["9d"])
    cfg0["run"]["cv_folds"] = inner_folds
    if not data_dir and isinstance(bundle.metadata.get("data_dir"), list):
        data_dir = bundle.metadata["data_dir"]  # trained on several directories: its names carry them
    index = open_index(data_dir or None)
    names = index.select(",".join(bundle.metadata["training_trials"]))
    identity = _sweep_identity(cfg0, names, folds, inner_folds, bundle.metadata.get("data_files"))
    return cfg0, index, names, identity


def existing_sweep_rows(model_dir, out_dir, folds: int = 5, inner_folds: int = 3, data_dir=None) -> list:
    """The rows already in ``out_dir/sweep_rows.jsonl`` for this model directory's sweep (same config,
    trials, folds and data files), whatever points they are; ``[]`` when there are none. Computes
    nothing (``togglecf export --max-bytes`` without ``--full-sweep``)."""
    rows_path = Path(out_dir) / "sweep_rows.jsonl"
    if not rows_path.is_file():
        return []
    identity = _sweep_setup(model_dir, data_dir, folds, inner_folds)[3]
    with ResultStore(rows_path, required=("row", "per_trial")) as store:
        return [rec["row"] for k, rec in store.done.items() if k.startswith(f"{identity}/")]


def _kib(v) -> str:
    return "-" if v is None else f"{v / 1024:.1f} KiB"


# ----------------------------------------------------------------------------------- results

def pareto_front(rows, size_key: str = "array_riscv_bytes", score_key: str = "mean_total") -> list:
    """The rows no other row beats on both size (smaller) and error (smaller)."""
    ok = [r for r in rows if r.get(size_key) is not None]
    return [r for r in ok if not any(o[size_key] <= r[size_key] and o[score_key] <= r[score_key]
                                     and (o[size_key] < r[size_key] or o[score_key] < r[score_key]) for o in ok)]


def tie_verdicts(rows) -> list:
    """Each row with ``p_vs_reference`` and ``vs_reference`` against the unpruned reference point:
    the paired per-trial Wilcoxon test of their held-out total errors (``report.paired_test``);
    ``tie`` when p ≥ 0.05 (the difference is inside the trial-to-trial spread), else ``better`` /
    ``worse``; ``reference`` for the reference itself, empty when either lacks per-trial errors
    (rows of a journal written before they were stored)."""
    ref = next((r for r in rows if r.get("reference")), None)
    base = (ref or {}).get("trial_totals")
    out = []
    for r in rows:
        r = dict(r)
        tt = r.get("trial_totals")
        if r.get("reference"):
            r.update(p_vs_reference=None, vs_reference="reference")
        elif base and tt and set(tt) == set(base):
            t = paired_test([tt[k] - base[k] for k in sorted(base)])
            r.update(p_vs_reference=t["p"], vs_reference="tie" if t["tie"] else ("better" if t["mean"] < 0 else "worse"))
        else:
            r.update(p_vs_reference=None, vs_reference="")
        out.append(r)
    return out


def choose_point(rows, max_bytes: int, size_key: str = "array_riscv_bytes") -> dict:
    """The most accurate row (lowest held-out mean total RMSE) whose ``size_key`` is within
    ``max_bytes``; ``ValueError`` naming the smallest available size when none fits."""
    fits = [r for r in rows if r.get(size_key) is not None and r[size_key] <= max_bytes]
    if not fits:
        sized = [r for r in rows if r.get(size_key) is not None]
        if not sized:
            raise ValueError(f"no sweep row has {size_key} (RISC-V sizes need {size_key.split('_')[0]} rows measured "
                             "with riscv64-unknown-elf-gcc; use the host size key or install the cross compiler)")
        small = min(sized, key=lambda r: r[size_key])
        raise ValueError(f"no sweep point fits in {max_bytes} bytes ({size_key}); the smallest is {small['key']} "
                         f"with {small[size_key]} bytes: add smaller points to the sweep or raise --max-bytes")
    return min(fits, key=lambda r: (r["mean_total"], r[size_key]))


_COLUMNS = ("key", "reference", "clf_trees", "clf_depth", "reg_trees", "reg_depth", "max_features", "features_used",
            "mean_total", "mean_heading", "mean_inclination", "max_total", "array_riscv_bytes", "array_host_bytes",
            "tl2cgen_riscv_bytes", "tl2cgen_host_bytes", "tl2cgen_q_riscv_bytes", "tl2cgen_q_host_bytes",
            "ram_bytes", "us_per_prediction", "pareto", "p_vs_reference", "vs_reference", "seconds")


def write_sweep_report(rows, out_dir, size_key: str = "array_riscv_bytes", max_bytes: int | None = None) -> dict:
    """``sweep.csv`` (every point, ``pareto`` marks the front on ``size_key``), ``pareto.csv``,
    ``pareto.png`` (error against size, front and budget marked). Returns the paths."""
    pd = require("pandas", extra="data", what="the pruning sweep's report")

    out = Path(out_dir)
    rows = tie_verdicts(rows)
    front = {r["key"] for r in pareto_front(rows, size_key)}
    df = pd.DataFrame([{c: (r.get(c) if c != "pareto" else r["key"] in front) for c in _COLUMNS} for r in rows])
    df = df.sort_values([size_key, "mean_total"], na_position="last")
    paths = {"sweep": out / "sweep.csv", "pareto": out / "pareto.csv", "plot": out / "pareto.png"}
    atomic_write_text(paths["sweep"], df.to_csv(index=False, float_format="%.6g"))
    atomic_write_text(paths["pareto"], df[df["pareto"]].to_csv(index=False, float_format="%.6g"))
    _plot(df, size_key, max_bytes, paths["plot"])
    return paths


def _plot(df, size_key, max_bytes, path):
    matplotlib = require("matplotlib", extra="plot", what="the pruning sweep's plot")

    matplotlib.use("Agg")
    plt = require("matplotlib.pyplot", extra="plot", what="the pruning sweep's plot")

    d = df[df[size_key].notna()]
    fig, ax = plt.subplots(figsize=(7, 4.2))
    for nf, g in d.groupby("max_features"):
        ax.scatter(g[size_key] / 1024, g["mean_total"], label=f"features: {'all' if nf == 0 else nf}", s=28)
    front = d[d["pareto"]].sort_values(size_key)
    ax.step(front[size_key] / 1024, front["mean_total"], where="post", color="k", lw=1, label="Pareto front")
    ref = d[d["reference"]]
    if len(ref):
        ax.scatter(ref[size_key] / 1024, ref["mean_total"], marker="*", s=160, color="crimson",
                   label="unpruned (reference)", zorder=5)
        ax.axhline(float(ref["mean_total"].iloc[0]) + 0.1, color="crimson", ls=":", lw=1, label="reference + 0.1°")
    if max_bytes:
        ax.axvline(max_bytes / 1024, color="grey", ls="--", lw=1, label=f"budget {max_bytes / 1024:.0f} KiB")
    ax.set_xscale("log")
    ax.set_xlabel(f"model object code [KiB] ({size_key.replace('_', ' ')}, gcc -Os)")
    ax.set_ylabel("held-out mean total RMSE [°]")
    ax.set_title("Toggling CF: model size vs. held-out BROAD error")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=7)
    atomic_write_bytes(path, png_bytes(fig))
    plt.close(fig)


def format_front(rows, size_key: str = "array_riscv_bytes") -> str:
    """The Pareto front as a text table (printed by the CLI)."""
    rows = tie_verdicts(rows)
    front = sorted(pareto_front(rows, size_key), key=lambda r: r[size_key])
    ref = next((r for r in rows if r["reference"]), None)
    lines = [f"{'point':<22} {'feat':>4} {'rv32 array':>10} {'rv32 tl2cgen':>12} {'RAM':>6} {'µs/pred':>7} "
             f"{'total°':>7} {'Δref°':>6} {'vs ref':>9}"]
    for r in front + ([ref] if ref and ref not in front else []):
        d = "" if ref is None else f"{r['mean_total'] - ref['mean_total']:+.3f}"
        verdict = r["vs_reference"] + ("" if r["p_vs_reference"] is None else f" p={r['p_vs_reference']:.2f}")
        lines.append(f"{r['key'] + ('*' if r['reference'] else ''):<22} {r['features_used']:>4} "
                     f"{_kib(r.get('array_riscv_bytes')):>10} {_kib(r.get('tl2cgen_riscv_bytes')):>12} "
                     f"{'-' if r.get('ram_bytes') is None else r['ram_bytes']:>6} {r['us_per_prediction']:>7.2f} "
                     f"{r['mean_total']:>7.3f} {d:>6} {verdict:>9}")
    lines.append("* reference: the model's own (unpruned) settings; sizes of the trees the filter walks")
    lines.append("vs ref: paired per-trial Wilcoxon test against the reference; tie = p >= 0.05 (inside the spread)")
    return "\n".join(lines)


# ------------------------------------------------------------------------------------------- CLI


def size_key(fmt: str, riscv: bool) -> str:
    """The sweep column that measures ``fmt``'s size: RISC-V object code, or the host's without it."""
    return SIZE_KEYS[fmt] if riscv else HOST_SIZE_KEYS[fmt]


