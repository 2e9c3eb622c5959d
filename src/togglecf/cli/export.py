"""``togglecf export``: a model directory as C (TL2cgen and/or compact arrays, checked against the
Python models) and the whole learned filter in C (``--filter``: the toggling CF, or the VQF core
with learned time constants); ``--max-bytes`` trains a pruned point first: the
best point of an existing pruning sweep, else the documented default point
(``run.prune.DEFAULT_EXPORT_POINT``); the sweep itself runs only with ``--full-sweep``. The parser is
``cli.parsers.add_export_parser``; this module is imported when the command runs (the ``export`` extra)."""
from __future__ import annotations

import shutil
import sys
from dataclasses import asdict, fields
from pathlib import Path

from togglecf.cli.parsers import add_export_parser
from togglecf.cli.prune import sweep_from_args
from togglecf.core.io import atomic_write_json
from togglecf.embedded.cfilter import export_c_filter
from togglecf.embedded.cvqf_toggling import export_c_vqf_toggling
from togglecf.embedded.forest_export import (
    ARRAY_LINK_MAIN,
    TOLERANCE,
    export_array_c,
    export_tl2cgen,
    model_sizes,
    tl2cgen_link_main,
    window_features_of_trials,
)
from togglecf.embedded.toolchain import RISCV_GCC, link_riscv
from togglecf.learn.models import load_bundle
from togglecf.registry import is_portable_file
from togglecf.run.config import load_config
from togglecf.run.prune import (
    DEFAULT_EXPORT_POINT,
    DEFAULT_EXPORT_SIZES,
    PrunePoint,
    choose_point,
    existing_sweep_rows,
    format_front,
    size_key,
    write_sweep_report,
)
from togglecf.run.train import run_training
from togglecf.toggling.pretrained import PRETRAINED_FILE

__all__ = ["add_export_parser", "cmd_export", "train_within_budget"]


def _point_from_sweep(args, rows, sweep_dir, key):
    write_sweep_report(rows, sweep_dir, key, args.max_bytes)
    print(format_front(rows, key))
    best = choose_point(rows, args.max_bytes, key)
    ref = next((r for r in rows if r["reference"]), None)
    vs = f" vs {ref['mean_total']:.3f}° unpruned" if ref else ""
    print(f"chosen for {args.max_bytes} bytes from the sweep in {sweep_dir} ({len(rows)} points): {best['key']} "
          f"({best[key]} bytes in the sweep, held-out mean total {best['mean_total']:.3f}°{vs})", file=sys.stderr)
    point = PrunePoint(**{f.name: best[f.name] for f in fields(PrunePoint) if f.name != "reference"})
    return point, best, ref


def train_within_budget(args) -> tuple:
    """``--max-bytes``: a pruned point within the budget, trained on the model's own training trials
    (gains on out-of-fold predictions, as ``togglecf train``): with ``--full-sweep`` the best point of
    the pruning sweep (run or resumed); else the best point of a sweep already in ``--sweep``; else
    ``DEFAULT_EXPORT_POINT``. Returns the new model directory and a report of the choice."""
    riscv = not args.no_riscv and shutil.which(RISCV_GCC) is not None
    key = size_key("tl2cgen" if args.format == "tl2cgen" else "array", riscv)
    sweep_dir = Path(args.sweep or Path(args.out) / "sweep")
    if args.full_sweep:
        rows = sweep_from_args(args, sweep_dir)
    else:
        rows = existing_sweep_rows(args.models, sweep_dir, args.folds, args.inner_folds, args.data)
    if rows:
        point, best, ref = _point_from_sweep(args, rows, sweep_dir, key)
        source = "sweep"
    else:
        point, best, ref, source = DEFAULT_EXPORT_POINT, None, None, "default"
        need = DEFAULT_EXPORT_SIZES[key]
        if args.max_bytes < need:
            raise ValueError(f"--max-bytes {args.max_bytes} is below the default pruned point's {need} bytes "
                             f"({key}, {DEFAULT_EXPORT_POINT.key}) and no sweep is in {sweep_dir}: add --full-sweep "
                             "to search smaller points (about 30 minutes on 2 cores)")
        print(f"no pruning sweep in {sweep_dir}: using the default point {point.key} (10 trees x depth 4, all "
              f"features; ~{need} bytes {key} in the sweep of the default models_broad); --full-sweep searches for "
              "this model", file=sys.stderr)
    bundle = load_bundle(args.models)
    cfg = point.apply(load_config(bundle.metadata["config"]))
    cfg["run"]["name"] = f"{cfg['run']['name']}-{point.key}"
    model_dir = Path(args.out) / "models"
    run_training(cfg, data_dir=args.data, trials=",".join(bundle.metadata["training_trials"]), out=model_dir,
                 cv=True, verbose=True)
    choice = {"max_bytes": args.max_bytes, "size_key": key, "source": source, "sweep_dir": str(sweep_dir),
              "point": best if best is not None else {"key": point.key, **asdict(point)}, "reference": ref,
              "source_models": str(args.models), "models": str(model_dir)}
    return model_dir, choice


def _fmt_size(v):
    return "-" if v is None else f"{v / 1024:.1f} KiB"


def _export_filter(args, riscv: bool, choice) -> tuple[dict, bool]:
    """The whole filter in C (``--filter``) beside the trees: its report, and whether the size budget
    of ``--max-bytes`` (``choice``) holds for the trees it ships."""
    filter_dir = Path(args.out) / "filter"
    ok = True
    fs = None if is_portable_file(args.models) else float(load_bundle(args.models).metadata["sampling_rate"])
    mode = "6D" if args.six_d else "9D"
    if args.filter == "vqf_toggling":
        rep = export_c_vqf_toggling(args.models, filter_dir, fs, use_mag=not args.six_d,
                                    forest_layout=args.forest_layout)
        forest_size = rep["object_sizes"]["tcf_forest.c"]  # {host, riscv, arm}: {text, data, bss, total}
        code = rep["code_bytes"]
        print(f"C learned VQF filter ({mode}, float32) in {filter_dir}: state {rep['state_bytes']} bytes; "
              f"trees + filter object code {_fmt_size(code['host'])} host, {_fmt_size(code['riscv'])} rv32imc, "
              f"{_fmt_size(code['arm'])} Cortex-M4F (of which trees {_fmt_size(rep['code_bytes_trees']['host'])} "
              f"host); kept by a --gc-sections link: {_fmt_size(rep['code_bytes_gc']['riscv'])} rv32imc, "
              f"{_fmt_size(rep['code_bytes_gc']['arm'])} Cortex-M4F; rate at init (tcf_vqft_init), "
              f"Arduino/PlatformIO library in {rep['library']}")
    else:
        rep = export_c_filter(args.models, filter_dir, fs, use_mag=not args.six_d, riscv=riscv,
                              forest_layout=args.forest_layout)
        forest_size = rep["object_sizes"]["tcf_forest.c"]
        linked = rep.get("linked_riscv")
        print(f"C filter ({mode}, float32) in {filter_dir}: state {rep['state_bytes']} bytes; "
              f"trees the filter walks {_fmt_size(forest_size['host']['total'])} host, "
              f"{_fmt_size(forest_size['riscv'] and forest_size['riscv']['total'])} rv32imc object code"
              + (f"; whole filter linked for rv32imc: {linked['flash'] / 1024:.1f} KiB flash" if linked else ""))
    rep["forest_bytes"] = forest_size
    if choice is not None:  # the budget holds for what ships: the filter's trees
        got = (forest_size["riscv"] or forest_size["host"])["total"]
        choice["filter_forest_bytes"] = got
        if got > args.max_bytes:
            hint = ("run the sweep with --full-sweep to find a smaller point" if choice["source"] == "default"
                    else "choose a smaller --max-bytes")
            print(f"error: the final models' trees take {got} bytes, over the budget of {args.max_bytes} "
                  f"(the sweep measured the folds' models): {hint}", file=sys.stderr)
            ok = False
    return rep, ok


def _export_portable(args) -> int:
    """A portable model file (the pretrained learned VQF by default): its learned VQF in C (OUT/filter).
    The file holds the compiled forest, not the XGBoost models the TL2cgen / array exports and their
    equivalence check start from, so those are not written."""
    if args.filter != "vqf_toggling":
        raise ValueError(f"--models {args.models}: a portable model file is a learned VQF: export it with "
                         "--filter vqf_toggling (the toggling CF needs a `togglecf train` model directory)")
    if args.max_bytes is not None:
        raise ValueError("--max-bytes retrains pruned models from a `togglecf train` model directory: give "
                         "--models DIR (a portable model file has no training setup to retrain)")
    riscv = not args.no_riscv and shutil.which(RISCV_GCC) is not None
    print(f"exporting the learned VQF of {args.models} (the C filter; no TL2cgen/array trees: the file holds "
          "the compiled forest, not the XGBoost models)", file=sys.stderr)
    rep, ok = _export_filter(args, riscv, None)
    atomic_write_json(Path(args.out) / "export_report.json", {"source": str(args.models), "filter": rep})
    return 0 if ok else 1


def cmd_export(args) -> int:
    if args.models is None:
        if args.filter != "vqf_toggling":
            raise ValueError("--models DIR is required for --filter toggling (a `togglecf train` model directory); "
                             "without it, --filter vqf_toggling exports the pretrained learned VQF")
        args.models = str(PRETRAINED_FILE)
    if is_portable_file(args.models):
        return _export_portable(args)
    choice = None
    if args.max_bytes is not None:
        args.models, choice = train_within_budget(args)
    X = None
    if not args.no_check:
        X = window_features_of_trials(load_bundle(args.models), args.trials, args.data)
        print(f"equivalence check on {len(X)} windows", file=sys.stderr)
    reports = {}
    formats = ("tl2cgen", "array") if args.format == "both" else (args.format,)
    riscv = not args.no_riscv and shutil.which(RISCV_GCC) is not None
    ok = True
    for fmt in formats:
        if fmt == "tl2cgen":
            rep = export_tl2cgen(args.models, args.out, quantize=args.quantize, X=X)
            model_sizes(rep, "firmware", riscv=riscv)
            if riscv:
                n_feat = len(load_bundle(args.models).schema.names)
                rep["linked_riscv"] = link_riscv([f for e in rep["models"].values() for f in e["firmware"]],
                                                 [rep["firmware_dir"]],
                                                 tl2cgen_link_main([f"tcf_{n}_" for n in rep["models"]], n_feat, 16))
        else:
            rep = export_array_c(args.models, args.out, X=X)
            model_sizes(rep, "source", riscv=riscv)
            if riscv:
                e = rep["models"]["forest"]
                rep["linked_riscv"] = link_riscv([e["source"]], [Path(e["source"]).parent], ARRAY_LINK_MAIN)
        reports[fmt] = rep
        title = fmt + (" (quantized)" if fmt == "tl2cgen" and args.quantize else "")
        print(f"{title}: object size (gcc -Os)   host        rv32imc     max|diff|")
        for name, e in rep["models"].items():
            d = e.get("max_abs_diff")
            d = "-" if d is None else f"{max(d.values()) if isinstance(d, dict) else d:.2e}"
            print(f"  {name:<12} {_fmt_size(e['size']['host']):>22} {_fmt_size(e['size']['riscv']):>11}   {d}")
        if rep.get("linked_riscv"):
            what = "all 7 models" if fmt == "tl2cgen" else "merged forest + softmax"
            print(f"  linked rv32imc picolibc program ({what}, soft-float, -Os): "
                  f"{rep['linked_riscv']['flash'] / 1024:.1f} KiB flash")
        if "ok" in rep:
            print(f"  equivalence (≤ {TOLERANCE:g}) on {rep['n_rows_checked']} windows: "
                  f"{'OK' if rep['ok'] else 'FAILED'} (max {rep['max_abs_diff']:.2e})")
            ok &= rep["ok"]
    if (Path(args.models) / "gains.json").is_file():
        reports["filter"], filter_ok = _export_filter(args, riscv, choice)
        ok &= filter_ok
    else:
        print(f"(no C filter: {Path(args.models) / 'gains.json'} is missing; `togglecf train` learns the gains)")
    if not riscv:
        print(f"(no RISC-V sizes: {RISCV_GCC} not installed or --no-riscv)")
    if choice is not None:
        reports["pruning"] = choice
    atomic_write_json(Path(args.out) / "export_report.json", reports)
    return 0 if ok else 1
