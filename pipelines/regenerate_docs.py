"""(Re)write the generated result tables of the documentation, ``docs/results/*.md``, from run outputs.

    python pipelines/regenerate_docs.py [--runs .] [--study reports/study] [--bench [--quick]] [--bench-dask]
                                        [--sweep build/embedded/default/sweep] [--export build/embedded/default]
                                        [--models models/default]
                                        [--lodo reports/lodo] [--per-sensor reports/per_sensor]
                                        [--per-sensor-half reports/per_sensor]
                                        [--headroom reports/headroom] [--out docs/results]

No number in the documentation is typed by hand: the pages include these files with
``pymdownx.snippets`` (``--8<-- "docs/results/study_summary.md"``). Each file starts with a line
saying which command wrote it and from which run (path, date, trials).

The run outputs are looked for in the folder ``--runs`` (default: the repository, where ``make run`` and
``togglecf train`` write them): each source's default below is relative to it. The tests point it at a
folder of their own, so what an earlier ``make run`` left in the checkout never changes their result.

What each source writes (a source that is absent leaves the existing files untouched, or writes a
placeholder saying how to produce it when there is no file yet):

* ``--study DIR`` (default ``reports/study``, what ``make run`` writes; read: ``per_trial.csv``,
  ``per_group.csv``, ``results.json``): ``study_summary.md`` (mean errors and speed per filter),
  ``study_highlights.md`` (the comparisons in words, computed), ``study_groups.md`` (per BROAD group,
  Δ to Madgwick, the fixed CF and VQF), ``study_ablations.md``, ``study_folds.md`` (learned gains and
  baseline TAGPs per fold), ``study_per_trial.md``.
* ``--bench``: runs ``pipelines/bench_filters.py``, ``bench_features.py``, ``bench_vqf_core.py``,
  ``bench_learned_vqf.py`` (the pretrained model the package ships), ``bench_cycles.py`` (the Cortex-M4F
  cycle estimate of the C filters; it trains its own small model) and, when ``--models`` holds a trained
  model, ``bench_toggling.py`` in their full mode (``--quick``: their quick mode, where a script has one) and
  captures the table each prints into ``bench_<name>.md``; ``--only NAME ...`` runs only those (the other
  tables are kept). ``--bench-dask`` also runs ``bench_dask.py`` (minutes; needs the dask
  extra) into ``bench_dask.md``.
* ``--sweep DIR`` (default ``build/embedded/default/sweep``; read: ``sweep.csv``, ``pareto.csv``):
  ``sweep.md``.
* ``--export DIR`` (default ``build/embedded/default``, what ``pipelines/export_embedded.py`` writes;
  read: ``filter/filter_report.json``): ``embedded_sizes.md``.
* ``--models DIR`` (default ``models/default``; read: ``cv_table.txt``): ``train_cv.md``.
* ``--lodo DIR`` (default ``reports/lodo``, ``make run``'s leave-one-dataset-out step): ``lodo.md``.
* ``--per-sensor DIR`` (default ``reports/per_sensor``, the per-sensor step of ``main.py --full`` or
  ``pipelines/per_sensor.py``): ``per_sensor.md``.
* ``--per-sensor-half DIR`` (default ``reports/per_sensor``, the same step's kept-back split or
  ``pipelines/per_sensor.py --half``): ``per_sensor_half.md``.
* ``--per-sensor-field-change DIR`` (default ``reports/per_sensor``, the learning curve with the field-change
  back-off searched in the scratch training too, or ``pipelines/per_sensor.py --field-change``):
  ``per_sensor_field_change.md``.
* ``--per-sensor-half-field-change DIR`` (default ``reports/per_sensor``, that split with it searched in the
  scratch training too, or ``pipelines/per_sensor.py --half --field-change``): ``per_sensor_half_field_change.md``.
* ``--headroom DIR`` (default ``reports/headroom``, ``pipelines/headroom.py`` or ``main.py --full``'s
  headroom step): ``headroom.md``.

The tables a pipeline writes with its own header (``lodo.md``, ``per_sensor.md``, ``headroom.md``, the
transfer tables) are copied as they are (``RUN_TABLES``): their first line names the command that made them.
* always: ``filter_defaults.md``, every filter's settings and defaults, from the code; and (with
  the default ``--out``) the figures of the docs that a command draws (``DOC_FIGURES``, e.g.
  ``docs/euler_05.png`` by ``togglecf plot euler``), when BROAD is found.

Each header names the run's command, its outputs' paths as that command writes them (never a
temporary checkout's path) and the code it ran (``core.provenance.source_revision``: the commit).
"""
from __future__ import annotations

import argparse
import datetime as _dt
import json
import math
import os
import re
import subprocess
import sys
from pathlib import Path
from typing import NamedTuple

import numpy as np

from togglecf.core.provenance import source_revision
from togglecf.report.study_report import (ABLATION_LABELS, ABLATION_ROWS, LABELS, MAIN_FILTERS,
                                          paired_comparison)

REPO = Path(__file__).resolve().parents[1]
SCRIPT = "python pipelines/regenerate_docs.py"

ABLATIONS = {a: ABLATION_LABELS.get(a, a) for a in ABLATION_ROWS}
LEVEL = 0.05  # |Δ| [°] below which a group comparison is called level
BENCHMARKS = ("bench_filters", "bench_features", "bench_vqf_core", "bench_toggling", "bench_learned_vqf",
              "bench_cycles")


# --------------------------------------------------------------------------------------------- helpers
def _now() -> str:
    return _dt.datetime.now().astimezone().strftime("%Y-%m-%d %H:%M %Z").strip()


def _mtime(path: Path) -> str:
    return _dt.datetime.fromtimestamp(path.stat().st_mtime).astimezone().strftime("%Y-%m-%d %H:%M %Z").strip()


#: the top folders of a run's outputs (``make run``, ``togglecf train``): a path is shown from there
_RUN_FOLDERS = ("reports", "build", "models")


def _shown(path) -> str:
    """A path as the header line shows it: relative to the repository when inside it; else from the
    run's own output folder on (``reports/…``, ``build/…``, ``models/…``: where the run's command
    writes it), never the temporary checkout it happened to run in."""
    p = Path(path).resolve()
    try:
        return p.relative_to(REPO).as_posix()
    except ValueError:
        pass
    parts = p.parts
    tops = [i for i, part in enumerate(parts) if part in _RUN_FOLDERS]
    return Path(*parts[tops[-1]:]).as_posix() if tops else p.name


def header(command: str, source: str) -> str:
    """The first line of every generated file: the command and the run it was made from."""
    return f"*Generated by `{command}` from {source}. Do not edit: rerun the command.*\n"


def write(out: Path, name: str, text: str) -> Path:
    out.mkdir(parents=True, exist_ok=True)
    path = out / name
    tmp = path.with_suffix(".tmp")
    tmp.write_text(text.rstrip("\n") + "\n", encoding="utf-8")
    os.replace(tmp, path)
    print(f"wrote {_shown(path)}")
    return path


def placeholder(out: Path, name: str, what: str, how: str) -> None:
    """Write a placeholder for a table that has never been generated (an existing one is kept)."""
    if (out / name).exists():
        print(f"kept {_shown(out / name)} ({what} not found)")
        return
    write(out, name, header(SCRIPT, "no run") + f"\n!!! note \"Not generated yet\"\n    {what} was not found when "
          f"this file was written ({_now()}). {how}\n")


def fmt(x, digits: int = 2) -> str:
    if x is None or (isinstance(x, float) and not math.isfinite(x)):
        return ""
    return f"{x:.{digits}f}"


def md_table(columns, rows) -> str:
    lines = ["| " + " | ".join(columns) + " |", "|" + "---|" * len(columns)]
    lines += ["| " + " | ".join(str(c) for c in r) + " |" for r in rows]
    return "\n".join(lines) + "\n"


# --------------------------------------------------------------------------------------------- study
def study_tables(study: Path, out: Path, command: str) -> None:
    import pandas as pd

    res = json.loads((study / "results.json").read_text())
    df = pd.read_csv(study / "per_trial.csv")
    long = pd.read_csv(study / "per_group.csv")
    trials = res.get("trials", sorted(df["trial"].unique()))
    n_folds = len(res.get("folds", []))
    total_s = res.get("timing", {}).get("total_s")
    code = f" at {res['code']}" if res.get("code") else ""
    # a study with its ablations (rows beyond the main filters) is the one of `--full`
    run = "python pipelines/main.py --full" if set(df["filter"]) - set(MAIN_FILTERS) else "make run"
    src = (f"the held-out study of `{run}` in `{_shown(study)}` (results.json of {_mtime(study / 'results.json')}"
           f"{code}; {len(trials)} BROAD trials, {n_folds} folds by whole trial"
           + (f", run time {total_s / 60:.1f} min" if total_s else "") + ")")
    head = header(command, src)
    wide = df.pivot_table(index="trial", columns="filter", values="total")
    # the known filters in their order, then any other non-ablation row the study wrote (never lost)
    mains = [f for f in MAIN_FILTERS if f in wide.columns] + sorted(
        f for f in wide.columns if f not in LABELS and f not in ABLATIONS and not f.endswith("_6d"))
    speed = df.groupby("filter")["us_per_sample"].median() if "us_per_sample" in df else {}

    rows = []
    for f in mains:
        sub = df[df["filter"] == f]
        label = LABELS.get(f, f)
        rows.append([f"**{label}**" if f == "toggling" else label, fmt(sub["total"].mean()),
                     fmt(sub["heading"].mean()), fmt(sub["inclination"].mean()), fmt(speed.get(f, float("nan")))])
    write(out, "study_summary.md", head + "\nMean RMSE in degrees over the trials (9D, each trial held out); "
          "µs/sample: median over the trials of the batch update, measured during the study run.\n\n"
          + md_table(["filter", "total [°]", "heading [°]", "inclination [°]", "µs/sample"], rows))

    tot = long[long["metric"] == "total"].set_index("group")
    have = [f for f in ("toggling", "madgwick", "cf", "vqf") if f in tot.columns]
    grows = []
    for g, r in tot.iterrows():
        row = [g, int(r["n_trials"])] + [fmt(r[f]) for f in have]
        if "toggling" in have:
            row += [fmt(r["toggling"] - r[f]) for f in have if f != "toggling"]
        grows.append(row)
    cols = ["group", "trials"] + have + ([f"Δ {f}" for f in have if f != "toggling"] if "toggling" in have else [])
    write(out, "study_groups.md", head + "\nMean total RMSE [°] per BROAD group; Δ = toggling − other "
          "(negative: the toggling CF is better).\n\n" + md_table(cols, grows))

    means = wide.mean(axis=0)
    extra_6d = sorted(a for a in means.index if a.endswith("_6d") and a not in ABLATIONS)
    arows = [[ABLATIONS.get(a, a), fmt(means[a])] for a in list(ABLATIONS) + extra_6d if a in means]
    if len(arows) > 1:
        write(out, "study_ablations.md", head + "\nMean total RMSE [°] over all trials, same folds; 6D rows "
              "with the constant heading offset removed.\n\n" + md_table(["variant", "total [°]"], arows))
    else:
        placeholder(out, "study_ablations.md", "A study with ablations",
                    "Run `python pipelines/main.py --full` (`make run` leaves the ablations out).")

    _study_highlights(out, head, tot, means, mains)

    frows = []
    for fi in res.get("folds", []):
        gains = fi.get("gains", {})
        g = ", ".join(f"{k} {_compact(v)}" for k, v in gains.items() if k not in ("train_objective", "train_objective_deg"))
        tagp = "; ".join(f"{k} {_compact(v.get('params', v))}" for k, v in fi.get("baseline_tagp", {}).items())
        frows.append([fi.get("fold"), ", ".join(t.split("_")[0] for t in fi.get("test", [])), g, tagp])
    write(out, "study_folds.md", head + "\nPer fold: the test trials (by number), the toggling CF's gains learned "
          "on the training trials, and each baseline's TAGP on the same training trials.\n\n"
          + md_table(["fold", "test trials", "learned gains", "baseline TAGPs"], frows))

    paired = paired_comparison(wide)
    if paired:
        write(out, "study_paired.md", head + "\n" + "\n".join(paired[2:]))
    prow = [[t] + [fmt(wide.loc[t, f]) for f in mains] for t in wide.index]
    write(out, "study_per_trial.md", head + "\nTotal RMSE [°] per trial, each with models, gains and baseline "
          "parameters fitted without it.\n\n" + md_table(["trial"] + mains, prow))


def transfer_tables(transfer: Path, study: Path, both: Path, out: Path, command: str) -> None:
    """The cross-dataset protocol of ``make run`` (``pipelines/main.py``): the rate and phone tables as
    written there (they carry their own header), and what training on both datasets changed."""
    import pandas as pd

    for name in ("rate", "phone"):
        src = transfer / f"{name}.md"
        if src.is_file():
            write(out, f"transfer_{name}.md", src.read_text())
        else:
            placeholder(out, f"transfer_{name}.md", f"`{_shown(src)}`", "Run `make run`.")
    if not ((both / "per_trial.csv").is_file() and (study / "per_trial.csv").is_file()
            and (transfer / "phone.json").is_file()):
        placeholder(out, "transfer_both.md", f"`{_shown(both)}`, `{_shown(study)}` and `{_shown(transfer)}/phone.json`",
                    "Run `python pipelines/main.py --full` with the phone data present.")
        return
    alone = pd.read_csv(study / "per_trial.csv").pivot_table(index="trial", columns="filter", values="total")
    joint = pd.read_csv(both / "per_trial.csv").pivot_table(index="trial", columns="filter", values="total")
    phone = json.loads((transfer / "phone.json").read_text())
    b_rows = [t for t in joint.index if t.split("/")[0] == "broad"]
    p_rows = [t for t in joint.index if t.split("/")[0] != "broad"]
    rows = []
    for f in ("vqf_toggling", "toggling", "vqf_core_defaults", "vqf", "madgwick", "cf", "ekf"):
        ph_alone = {"vqf_core_defaults": "vqf_core"}.get(f, f)
        cells = [alone[f].mean() if f in alone else float("nan"),
                 joint.loc[b_rows, f].mean() if f in joint else float("nan"),
                 np.mean([r["total"] for r in phone[ph_alone].values()]) if ph_alone in phone else float("nan"),
                 joint.loc[p_rows, f].mean() if f in joint else float("nan")]
        rows.append([LABELS.get(f, f)] + [fmt(c) for c in cells])
    src = (f"`{_shown(study)}` (BROAD alone, held out), `{_shown(both)}` (BROAD + phone, folds by whole trial over "
           f"both, held out; {len(b_rows)} BROAD and {len(p_rows)} phone trials) and `{_shown(transfer)}/phone.json` "
           "(trained on all of BROAD)")
    write(out, "transfer_both.md", header(command, src) + "\nMean total RMSE [°]. Trained filters: held out in both "
          "studies; on the phone, 'BROAD only' means models trained on all BROAD trials (it never saw a phone trial). "
          "The classic filters are at their fold TAGP in the studies and at their defaults in the BROAD-only phone "
          "column.\n\n" + md_table(["filter", "BROAD, trained on BROAD", "BROAD, trained on both",
                                       "phone, trained on BROAD", "phone, trained on both"], rows))


def spread_table(studies: list[Path], out: Path, command: str) -> None:
    """``study_spread.md``: each filter's mean total RMSE in every fold assignment (one study output
    each) and the mean ± standard deviation over the assignments."""
    import pandas as pd

    means = {}
    for s in studies:
        res = json.loads((s / "results.json").read_text())
        df = pd.read_csv(s / "per_trial.csv")
        label = f"assignment {res['fold_seed']}" if "fold_seed" in res else _shown(s)
        means[label] = df.groupby("filter")["total"].mean()
    table = pd.DataFrame(means)
    order = [f for f in MAIN_FILTERS if f in table.index] + sorted(f for f in table.index if f not in MAIN_FILTERS)
    rows = []
    for f in order:
        vals = table.loc[f].dropna()
        if len(vals) < 2:
            continue
        rows.append([LABELS.get(f, f)] + [fmt(table.loc[f, c]) for c in table.columns]
                    + [f"{vals.mean():.2f} ± {vals.std(ddof=1):.2f}"])
    src = f"{len(studies)} study runs with different fold assignments ({', '.join(_shown(s) for s in studies)})"
    write(out, "study_spread.md", header(command, src) + "\nMean total RMSE [°] over the held-out trials for "
          "each fold assignment (5 folds by whole trial; assignment 0 is the standard round-robin, the others "
          "a seeded shuffle), and mean ± sample standard deviation over the assignments. Differences smaller "
          "than this spread are ties.\n\n" + md_table(["filter", *table.columns, "mean ± sd"], rows))


def _compact(v) -> str:
    if isinstance(v, dict):
        return "{" + ", ".join(f"{k}={_compact(x)}" for k, x in v.items()) + "}"
    if isinstance(v, (list, tuple)):
        return "(" + ", ".join(_compact(x) for x in v) + ")"
    if isinstance(v, float):
        return f"{v:g}"
    return str(v)


def _study_highlights(out, head, tot, means, mains) -> None:
    if "toggling" not in means:
        placeholder(out, "study_highlights.md", "A study with the toggling CF", "Run `make run`.")
        return
    t = means["toggling"]
    lines = []
    for f in ("madgwick", "cf", "vqf", "ekf", "aqua", "mahony"):
        if f in means:
            d = t - means[f]
            word = "better" if d < 0 else "worse"
            lines.append(f"- against {LABELS[f].split(' (')[0]}: {abs(d):.2f}° {word} on average "
                         f"({t:.2f}° vs {means[f]:.2f}°)")
    for f in ("madgwick", "vqf"):
        if f not in tot.columns:
            continue
        d = (tot["toggling"] - tot[f]).drop("all_trials", errors="ignore").dropna()
        parts = {"better": [], "level (within 0.05°)": [], "worse": []}
        for g, v in d.items():
            parts["better" if v <= -LEVEL else "worse" if v >= LEVEL else "level (within 0.05°)"].append(
                f"{g} ({v:+.2f}°)")
        name = LABELS[f].split(" (")[0]
        lines.append(f"- per group against {name}: " + "; ".join(f"{k} on {', '.join(v)}" for k, v in parts.items()
                                                                  if v))
    abl = {a: means[a] for a in ("toggling_only", "noise_only", "ransac_off") if a in means}
    if abl:
        best = min(abl, key=abl.get)
        lines.append(f"- ablations: the best variant is *{ABLATIONS[best]}* ({abl[best]:.2f}°), the full filter "
                     f"{t:.2f}°")
    write(out, "study_highlights.md", head + "\nThe toggling CF (held out) against the others, total RMSE; "
          "group means over the trials of each BROAD group present.\n\n" + "\n".join(lines) + "\n")


# --------------------------------------------------------------------------------------------- benchmarks
def _load_average() -> str:
    try:
        return f"{os.getloadavg()[0]:.2f}"
    except OSError:
        return "?"


def _supports(script: Path, flag: str) -> bool:
    r = subprocess.run([sys.executable, str(script), "--help"], capture_output=True, text=True, cwd=REPO, check=False)
    return flag in r.stdout


def run_benchmark(name: str, out: Path, quick: bool, extra=(), command: str = SCRIPT) -> None:
    script = REPO / "pipelines" / f"{name}.py"
    args = list(extra)
    mode = "full mode"
    if quick:
        if _supports(script, "--quick"):
            args.append("--quick")
            mode = "quick mode"
        else:
            mode = "full mode (the script has no quick mode)"
    cmd = ["python", f"pipelines/{name}.py", *(_shown(a) if Path(a).is_absolute() else a for a in args)]
    load = _load_average()
    print("running " + " ".join(cmd), flush=True)
    r = subprocess.run([sys.executable, str(script), *args], capture_output=True, text=True, cwd=REPO, check=False)
    if r.returncode != 0:
        print(f"{name} failed (exit {r.returncode}); {name}.md not changed:\n{r.stderr[-2000:]}", file=sys.stderr)
        placeholder(out, f"{name}.md", f"A successful run of `{' '.join(cmd)}`", f"Run `{command}`.")
        return
    src = (f"`{' '.join(cmd)}` ({mode}) run on {_now()} at {source_revision(REPO)}, {os.cpu_count()} cores, load "
           f"average {load} before the run")
    body = r.stdout.strip()
    table = _written_markdown(body)
    if table is not None:  # the script wrote its own Markdown table: include it, and the rest of its output
        rest = "\n".join(ln for ln in body.splitlines() if not ln.startswith(("|", "wrote ")))
        rest = re.sub(r"\n{3,}", "\n\n", rest).strip()
        write(out, f"{name}.md", header(command, src) + "\n" + table + "\n\nIts console output:\n\n```text\n"
              + rest + "\n```\n")
        return
    write(out, f"{name}.md", header(command, src) + "\nIts output, as printed (ratios are against a reference "
          "measured in the same run; absolute times depend on the machine and its load):\n\n```text\n"
          + body + "\n```\n")


def _written_markdown(stdout: str) -> str | None:
    """The Markdown file a benchmark says it wrote (``wrote PATH.md``), without its title line."""
    m = re.search(r"wrote (\S+\.md)\b", stdout)
    if not m:
        return None
    path = Path(m.group(1)) if Path(m.group(1)).is_absolute() else REPO / m.group(1)
    if not path.is_file():
        return None
    lines = path.read_text(encoding="utf-8").strip().splitlines()
    if lines and lines[0].startswith("# "):
        lines = lines[1:]
    return "\n".join(lines).strip()


# --------------------------------------------------------------------------------------------- sweep
def sweep_tables(sweep: Path, out: Path, command: str) -> None:
    import pandas as pd

    df = pd.read_csv(sweep / "sweep.csv")
    src = f"the pruning sweep in `{_shown(sweep)}` (sweep.csv of {_mtime(sweep / 'sweep.csv')}; {len(df)} points)"
    ref = df[df["reference"].astype(bool)] if "reference" in df else df.iloc[:0]
    ref_total = float(ref["mean_total"].iloc[0]) if len(ref) else float("nan")

    def kib(x):
        return "" if pd.isna(x) else f"{x / 1024:.1f}"

    rows = []
    for _, r in df.iterrows():
        trees = (f"{int(r['clf_trees'])} × {int(r['clf_depth'])}" if r["clf_trees"] == r["reg_trees"] and
                 r["clf_depth"] == r["reg_depth"] else
                 f"{int(r['clf_trees'])} × {int(r['clf_depth'])} / {int(r['reg_trees'])} × {int(r['reg_depth'])}")
        nf = "all" if int(r["max_features"]) == 0 else str(int(r["max_features"]))
        name = f"{trees}, {nf}" + (" (unpruned)" if bool(r.get("reference", False)) else "")
        rows.append([f"**{name}**" if bool(r.get("pareto", False)) else name, kib(r.get("array_riscv_bytes")),
                     kib(r.get("tl2cgen_riscv_bytes")), kib(r.get("tl2cgen_q_riscv_bytes")),
                     fmt(r["mean_total"], 3), fmt(r["mean_total"] - ref_total, 2),
                     fmt(r.get("us_per_prediction"), 2)])
    text = (header(command, src) + "\nEach point: trees per booster × depth (classifier / regressors when they differ) and the "
            "number of most important features the trees may split on. Sizes: rv32imc object code (`gcc -Os`) of "
            "the trees the filter walks, largest over the folds, in KiB; held-out: mean total RMSE [°] of the "
            "toggling filter with those models under the study's protocol; Δ against the unpruned models; "
            "**bold**: on the Pareto front (size vs. held-out error).\n\n"
            + md_table(["point (trees × depth, features)", "rv32 array", "rv32 TL2cgen", "TL2cgen quantized",
                        "held-out total [°]", "Δ vs unpruned [°]", "µs/prediction"], rows))
    write(out, "sweep.md", text)


def embedded_sizes(report_path: Path, out: Path, command: str) -> None:
    rep = json.loads(report_path.read_text())
    src = f"the C filter export `{_shown(report_path)}` ({_mtime(report_path)})"
    # the C takes its rate at init: window and hop are at the harness's default rate, the state holds the
    # feature ring for the largest rate (max_fs)
    rows = [["default rate of the harness [Hz] (the C takes its rate at init)", fmt(rep.get("fs"), 3)],
            ["largest rate `TCF_MAX_FS` [Hz] (the feature ring is sized for it)", fmt(rep.get("max_fs"), 0)],
            ["mode", "9D" if rep.get("use_mag", True) else "6D"],
            ["window / hop at the default rate [samples]", f"{rep.get('window')} / {rep.get('hop')}"],
            ["trees walked / nodes", f"{rep.get('n_trees')} / {rep.get('n_nodes')}"],
            ["outputs left out (noise weight 0)", ", ".join(rep.get("dropped_outputs") or []) or "none"],
            ["filter state `sizeof(tcf_filter_t)` [bytes]", rep.get("state_bytes", "")]]
    linked = rep.get("linked_riscv")
    if linked:
        rows.append(["linked rv32imc picolibc program, flash (text + data) [KiB]", fmt(linked["flash"] / 1024, 1)])
    for f, v in (rep.get("object_sizes") or {}).items():
        for target in ("host", "riscv"):
            if v.get(target):
                rows.append([f"`{f}` object code, {target} `gcc -Os` [KiB]", fmt(v[target]["total"] / 1024, 1)])
    write(out, "embedded_sizes.md", header(command, src) + "\n" + md_table(["quantity", "value"], rows))


# --------------------------------------------------------------------------------------------- models, defaults
def train_cv(models: Path, out: Path, command: str) -> None:
    meta = json.loads((models / "metadata.json").read_text())
    n = len(meta.get("training_trials", []))
    src = f"the model directory `{_shown(models)}` (cv_table.txt of {_mtime(models / 'cv_table.txt')}; {n} trials)"
    write(out, "train_cv.md", header(command, src) + "\nThe cross-validation table `togglecf train` printed "
          "(folds by whole trial, held-out windows):\n\n```text\n" + (models / "cv_table.txt").read_text().strip()
          + "\n```\n")


#: the docs' figures that a command draws: file (under docs/) -> the `togglecf` command's arguments
DOC_FIGURES = {"euler_05.png": ["plot", "euler", "--trial", "05", "--filters", "madgwick,cf"]}


def doc_figures(docs: Path) -> None:
    """Draw every figure of ``DOC_FIGURES`` with its command (BROAD found as `evaluate` finds it); a
    figure whose command fails (no data here) is kept as it is, and said so."""
    for name, args in DOC_FIGURES.items():
        cmd = [sys.executable, "-m", "togglecf", *args, "--out", str(docs / name)]
        r = subprocess.run(cmd, capture_output=True, text=True, cwd=REPO, check=False)
        shown = "togglecf " + " ".join(args) + f" --out docs/{name}"
        if r.returncode != 0:
            print(f"kept docs/{name}: `{shown}` failed: {r.stderr.strip().splitlines()[-1:]}", file=sys.stderr)
        else:
            print(f"wrote docs/{name} (`{shown}`)")


def filter_defaults(out: Path, command: str) -> None:
    import dataclasses

    from togglecf.filters import FilterSettings
    from togglecf.registry import CATALOG, CLASSIC_NAMES

    base = {f.name for f in dataclasses.fields(FilterSettings)}
    rows = []
    for name in CLASSIC_NAMES:
        entry = CATALOG[name]
        settings_cls = entry.cls.Settings
        fields = [f"{f.name} = {_compact(f.default)}" for f in dataclasses.fields(settings_cls)
                  if f.name not in base and f.default is not dataclasses.MISSING]
        rows.append([f"`{name}`", entry.description, f"`{entry.cls.__module__}.{entry.cls.__name__}`",
                     f"`{settings_cls.__name__}`", "; ".join(fields)])
    write(out, "filter_defaults.md", header(command, f"the code of `togglecf.filters` ({_now()})") +
          "\nThe classic filters of the filter table (`togglecf.registry.CATALOG`, kind `classic`; CLI names) and "
          "their settings' defaults, read from the dataclasses (common settings of `FilterSettings` left out).\n\n"
          + md_table(["CLI name", "what", "class", "settings", "defaults"], rows))


# --------------------------------------------------------------------------------------------- run tables
class RunTable(NamedTuple):
    """A table a pipeline writes with its own header, copied as it is: option ``--<option>`` names the
    folder (default ``folder``, under ``--runs``) that holds ``name``; ``what`` it is, ``how`` to make it."""

    option: str
    folder: str
    name: str
    what: str
    how: str


RUN_TABLES = (
    RunTable("lodo", "reports/lodo", "lodo.md", "the leave-one-dataset-out output of `make run`",
             "Run `make run` with the phone data beside BROAD."),
    RunTable("per_sensor", "reports/per_sensor", "per_sensor.md",
             "the per-sensor output of `python pipelines/main.py --full` or `pipelines/per_sensor.py`",
             "Run `python pipelines/per_sensor.py` (or `python pipelines/main.py --full`)."),
    RunTable("per_sensor_half", "reports/per_sensor", "per_sensor_half.md",
             "the kept-back check's split of `python pipelines/main.py --full` or `pipelines/per_sensor.py --half`",
             "Run `python pipelines/per_sensor.py --half` (or `python pipelines/main.py --full`)."),
    RunTable("per_sensor_field_change", "reports/per_sensor", "per_sensor_field_change.md",
             "the per-sensor learning curve with the field-change back-off searched, of `python pipelines/main.py "
             "--full` or `pipelines/per_sensor.py --field-change`",
             "Run `python pipelines/per_sensor.py --field-change` (or `python pipelines/main.py --full`)."),
    RunTable("per_sensor_half_field_change", "reports/per_sensor", "per_sensor_half_field_change.md",
             "the kept-back check's split with the field-change back-off searched, of `python pipelines/main.py "
             "--full` or `pipelines/per_sensor.py --half --field-change`",
             "Run `python pipelines/per_sensor.py --half --field-change` (or `python pipelines/main.py --full`)."),
    RunTable("headroom", "reports/headroom", "headroom.md", "the headroom over VQF (pipelines/headroom.py)",
             "Run `python pipelines/headroom.py` (or `python pipelines/main.py --full`)."),
    RunTable("travel", "reports/travel", "travel.md", "what could set VQF's time constants on a dataset left out "
             "(pipelines/travel.py)", "Run `python pipelines/travel.py` (or `python pipelines/main.py --full`)."),
)


def copy_run_table(table: RunTable, given, runs: Path, out: Path, parser) -> None:
    """Copy ``table`` from the folder ``given`` (an option's value) or its default under ``runs``; a
    missing default leaves a placeholder, a missing given folder is an error."""
    folder = Path(given) if given else runs / table.folder
    if (folder / table.name).is_file():
        write(out, table.name, (folder / table.name).read_text())
    elif given:
        parser.error(f"{folder}: no {table.name} ({table.how})")
    else:
        placeholder(out, table.name, f"`{table.folder}/{table.name}`", table.how)


# --------------------------------------------------------------------------------------------- main
def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0], epilog=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--runs", default=str(REPO), metavar="DIR",
                   help="the folder whose reports/, build/ and models/ hold the run outputs: every source's "
                        "default is under it (default: the repository)")
    p.add_argument("--study", default=None, metavar="DIR", help="study output (default: reports/study if present)")
    p.add_argument("--bench", action="store_true", help="run the benchmarks and capture their tables")
    p.add_argument("--quick", action="store_true", help="with --bench: the benchmarks' quick modes")
    p.add_argument("--only", nargs="+", choices=BENCHMARKS, default=None, metavar="NAME",
                   help="with --bench: run only these benchmarks (e.g. bench_cycles); the other tables are kept")
    p.add_argument("--bench-dask", action="store_true", help="also run bench_dask.py (minutes)")
    p.add_argument("--sweep", default=None, metavar="DIR",
                   help="pruning sweep directory (default: build/embedded/default/sweep if present)")
    p.add_argument("--export", default=None, metavar="DIR",
                   help="a C filter export (default: build/embedded/default if present) -> embedded_sizes.md")
    p.add_argument("--models", default=None, metavar="DIR",
                   help="trained model directory (default: models/default if present)")
    p.add_argument("--spread", default=None, metavar="DIRS",
                   help="comma-separated study outputs of different fold assignments -> study_spread.md")
    p.add_argument("--transfer", default=None, metavar="DIR",
                   help="the cross-dataset outputs of `make run` (default: reports/transfer if present; with "
                        "reports/study_both)")
    for table in RUN_TABLES:
        p.add_argument(f"--{table.option.replace('_', '-')}", default=None, metavar="DIR",
                       help=f"{table.what} (default: {table.folder} if present)")
    p.add_argument("--out", default=str(REPO / "docs" / "results"), metavar="DIR")
    args = p.parse_args(argv)
    out = Path(args.out)
    runs = Path(args.runs)

    study = Path(args.study) if args.study else runs / "reports" / "study"
    if (study / "results.json").is_file():
        study_tables(study, out, " ".join([SCRIPT, "--study", _shown(study) if args.study else "reports/study"]))
    else:
        if args.study:
            p.error(f"{study}: no results.json (run `make run` or pipelines/run_all.py --out {study})")
        for name in ("study_summary.md", "study_highlights.md", "study_groups.md", "study_ablations.md",
                     "study_folds.md", "study_per_trial.md"):
            placeholder(out, name, "The study output `reports/study/results.json`",
                        f"Run `make run`, then `{SCRIPT}`.")

    transfer = Path(args.transfer) if args.transfer else runs / "reports" / "transfer"
    if transfer.is_dir():
        transfer_tables(transfer, study, transfer.parent / "study_both", out,
                        f"{SCRIPT} --transfer {_shown(transfer) if args.transfer else 'reports/transfer'}")
    elif args.transfer:
        p.error(f"{transfer}: not found (run `make run`)")

    for table in RUN_TABLES:
        copy_run_table(table, getattr(args, table.option), runs, out, p)

    if args.spread:
        dirs = [Path(d) for d in args.spread.split(",") if d]
        spread_table(dirs, out, f"{SCRIPT} --spread {args.spread}")

    models = Path(args.models) if args.models else runs / "models" / "default"
    if (models / "cv_table.txt").is_file() and (models / "metadata.json").is_file():
        train_cv(models, out, f"{SCRIPT} --models {_shown(models)}")
    else:
        if args.models:
            p.error(f"{models}: no cv_table.txt/metadata.json (run `togglecf train --out {models}`)")
        placeholder(out, "train_cv.md", "A trained model directory `models/default`",
                    f"Run `togglecf train`, then `{SCRIPT} --models models/default`.")

    sweep = Path(args.sweep) if args.sweep else runs / "build" / "embedded" / "default" / "sweep"
    if (sweep / "sweep.csv").is_file():
        sweep_tables(sweep, out, f"{SCRIPT} --sweep {_shown(sweep)}")
    else:
        if args.sweep:
            p.error(f"{sweep}: no sweep.csv (run `togglecf prune --models models/default --out {sweep}`)")
        how = ("Run `togglecf prune --models models/default --out build/embedded/default/sweep` (or "
               f"`python pipelines/export_embedded.py`), then `{SCRIPT} --sweep build/embedded/default/sweep`.")
        placeholder(out, "sweep.md", "The pruning sweep `build/embedded/default/sweep/sweep.csv`", how)

    export = Path(args.export) if args.export else runs / "build" / "embedded" / "default"
    report = export / "filter" / "filter_report.json"
    if report.is_file():
        embedded_sizes(report, out, f"{SCRIPT} --export {_shown(export)}")
    else:
        if args.export:
            p.error(f"{export}: no filter/filter_report.json (run `python pipelines/export_embedded.py --out {export}`)")
        placeholder(out, "embedded_sizes.md", "An export's `build/embedded/default/filter/filter_report.json`",
                    f"Run `python pipelines/export_embedded.py`, then `{SCRIPT} --export build/embedded/default`.")

    bench_cmd = f"{SCRIPT} --bench" + (" --quick" if args.quick else "") + (f" --only {' '.join(args.only)}"
                                                                             if args.only else "")
    if args.bench:
        for name in args.only or BENCHMARKS:
            extra = []
            if name == "bench_toggling":
                if not (models / "metadata.json").is_file():
                    placeholder(out, f"{name}.md", f"A trained model directory `{_shown(models)}`",
                                f"Run `togglecf train`, then `{SCRIPT} --bench`.")
                    continue
                extra = ["--models", str(models)]
            run_benchmark(name, out, args.quick, extra, bench_cmd)
    else:
        for name in BENCHMARKS:
            placeholder(out, f"{name}.md", "A benchmark run", f"Run `{SCRIPT} --bench`.")
    if args.bench_dask:
        run_benchmark("bench_dask", out, args.quick, (), f"{SCRIPT} --bench-dask")
    else:
        placeholder(out, "bench_dask.md", "A run of `pipelines/bench_dask.py`", f"Run `{SCRIPT} --bench-dask`.")

    filter_defaults(out, SCRIPT)
    if out.resolve() == (REPO / "docs" / "results").resolve():
        doc_figures(REPO / "docs")
    return 0


if __name__ == "__main__":
    sys.exit(main())
