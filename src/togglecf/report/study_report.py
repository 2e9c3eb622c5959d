"""The study's report directory: CSV tables, a markdown summary and the plots.

Written files (all atomically):
``per_trial.csv`` (one row per trial and filter, all metrics), ``per_trial_total.csv`` (total
RMSE, trials x filters), ``per_group.csv`` (group means), ``summary.md``, ``results.json``,
``plots/error_<trial>.png`` (total error over time of VQF, Madgwick, the fixed CF and the
toggling CF), ``plots/groups.png`` (grouped bars per BROAD group), ``plots/timeline_<trial>.png``
(α and the predicted state over the ground-truth motion state). Every filter has its colour and
line style from ``report.style`` (toggling blue, VQF grey, Madgwick red, fixed CF green, ...), the
same as in ``report.plots``.
"""
from __future__ import annotations

import io
from pathlib import Path

import numpy as np
import pandas as pd

from togglecf.core.io import atomic_write_bytes, atomic_write_json, atomic_write_text
from togglecf.learn.labels import make_targets
from togglecf.report.style import color, style

__all__ = ["write_report", "group_table", "error_figure", "groups_figure", "timeline_figure", "png_bytes"]

MAIN_FILTERS = ("toggling", "vqf", "madgwick", "cf", "mahony", "aqua", "ekf")
#: filters drawn in ``error_<trial>.png`` (back to front) and, in this order, in ``groups.png``
ERROR_PLOT_FILTERS = ("vqf", "madgwick", "cf", "toggling")
ABLATION_ROWS = ("toggling", "toggling_only", "noise_only", "ransac_off", "toggling_6d", "cf_6d", "madgwick_6d",
                 "vqf_6d")


def group_table(df: pd.DataFrame, groups: dict, metric: str = "total") -> pd.DataFrame:
    """Group x filter: mean of the trials' RMSE over the trials of the group that were run."""
    wide = df.pivot_table(index="trial", columns="filter", values=metric)
    out = {}
    for g, members in groups.items():
        present = [t for t in members if t in wide.index]
        if present:
            row = wide.loc[present].mean(axis=0)
            row["n_trials"] = len(present)
            out[g] = row
    return pd.DataFrame(out).T


def _fmt(x):
    return "" if pd.isna(x) else f"{x:.2f}"


def _md_table(df: pd.DataFrame, cols, index_name) -> str:
    cols = [c for c in cols if c in df.columns]
    lines = [f"| {index_name} | " + " | ".join(cols) + " |", "|---" * (len(cols) + 1) + "|"]
    for idx, row in df.iterrows():
        lines.append(f"| {idx} | " + " | ".join(_fmt(row[c]) if c != "n_trials" else str(int(row[c])) for c in cols)
                     + " |")
    return "\n".join(lines)


def write_report(out, result: dict, series: dict, timelines: dict, trials: dict):
    out = Path(out)
    df = pd.DataFrame(result["rows"])
    atomic_write_text(out / "per_trial.csv", df.to_csv(index=False, float_format="%.6f"))
    wide = df.pivot_table(index="trial", columns="filter", values="total")
    atomic_write_text(out / "per_trial_total.csv", wide.to_csv(float_format="%.4f"))
    groups = {g: m for g, m in result["groups"].items()}
    per_group = {m: group_table(df, groups, m) for m in ("total", "heading", "inclination", "roll", "pitch", "yaw",
                                                          "us_per_sample") if m in df}
    long = pd.concat({m: t for m, t in per_group.items()}, names=["metric", "group"])
    atomic_write_text(out / "per_group.csv", long.to_csv(float_format="%.4f"))
    atomic_write_text(out / "summary.md", _summary(df, per_group, result))
    atomic_write_json(out / "results.json", {k: v for k, v in result.items() if k != "rows"} | {
        "mean_total": wide.mean(axis=0).to_dict()})
    _plots(out / "plots", df, per_group["total"], series, timelines, trials)


def _summary(df, per_group, result) -> str:
    wide = df.pivot_table(index="trial", columns="filter", values="total")
    speed = df.groupby("filter")["us_per_sample"].median() if "us_per_sample" in df else pd.Series(dtype=float)
    n = len(result["trials"])
    lines = [f"# Held-out study: toggling CF vs classic filters and VQF ({n} BROAD trials, 9D)", ""]
    lines += ["Every trial is filtered with models and gains trained **without** it "
              f"({len(result['folds'])} folds by whole trial); each baseline runs at its TAGP over the same "
              "training folds; VQF at its defaults. RMSE in degrees over BROAD's movement samples.", ""]
    if result["missing"]:
        lines += [f"Trials not present ({len(result['missing'])} of BROAD's 39): " + ", ".join(result["missing"]), ""]
    mains = [f for f in MAIN_FILTERS if f in wide.columns]
    lines += ["## Mean over all trials", "", "| filter | total | heading | inclination | µs/sample (median) |",
              "|---|---|---|---|---|"]
    for f in mains:
        sub = df[df["filter"] == f]
        lines.append(f"| {f} | {sub['total'].mean():.2f} | {sub['heading'].mean():.2f} | "
                     f"{sub['inclination'].mean():.2f} | {_fmt(speed.get(f, np.nan))} |")
    lines.append("")
    tot = per_group["total"]
    if "toggling" in tot:
        lines += ["## Toggling CF vs Madgwick, fixed CF and VQF per BROAD group (total RMSE)", "",
                  "Δ = toggling − other (negative: toggling is better).", ""]
        cmp = pd.DataFrame(index=tot.index)
        for f in ("toggling", "madgwick", "cf", "vqf"):
            if f in tot:
                cmp[f] = tot[f]
        for f in ("madgwick", "cf", "vqf"):
            if f in tot:
                cmp[f"Δ {f}"] = tot["toggling"] - tot[f]
        cmp["n_trials"] = tot["n_trials"]
        lines += [_md_table(cmp, list(cmp.columns), "group"), ""]
    abl = [c for c in ABLATION_ROWS if c in wide.columns]
    if len(abl) > 1:
        lines += ["## Ablations (mean total RMSE over all trials; 6D rows with the heading offset removed)", "",
                  "| variant | total |", "|---|---|"]
        desc = {"toggling": "toggling + noise removal (the filter)", "toggling_only": "toggling only (η̂ = 0)",
                "noise_only": "noise removal only (one gain, no rest bias)", "ransac_off": "both, models without RANSAC",
                "toggling_6d": "both, 6D", "cf_6d": "fixed CF, 6D", "madgwick_6d": "Madgwick, 6D", "vqf_6d": "VQF, 6D"}
        for a in abl:
            lines.append(f"| {desc.get(a, a)} | {wide[a].mean():.2f} |")
        lines.append("")
    lines += ["## Folds", ""]
    for fi in result["folds"]:
        tagp = ", ".join(f"{k} {v['params']}" for k, v in fi.get("baseline_tagp", {}).items())
        lines.append(f"- fold {fi['fold']}: test {', '.join(fi['test'])}; models {fi['train_s']:.0f} s, gains "
                     f"{fi['gains_s']:.0f} s; learned gains {fi['gains']}; baseline TAGPs: {tagp}")
    lines += ["", f"Total time {result['timing']['total_s']:.0f} s (baseline grids "
              f"{result['timing']['baseline_grids_s']:.0f} s).", ""]
    lines += ["## Per trial (total RMSE)", "", _md_table(wide[[c for c in mains]], mains, "trial"), ""]
    return "\n".join(lines)


def png_bytes(fig) -> bytes:
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=90, bbox_inches="tight")
    return buf.getvalue()


def error_figure(name: str, trial, series: dict):
    """Total error [deg] over time of the filters of ``ERROR_PLOT_FILTERS`` found in ``series``
    (filter -> per-sample error), each in its ``report.style``; line labels are the filter names."""
    import matplotlib.pyplot as plt

    time_s = np.arange(trial.n_samples) / trial.fs
    fig, ax = plt.subplots(figsize=(10, 3.2))
    for f in ERROR_PLOT_FILTERS:
        if f in series:
            ax.plot(time_s, series[f], label=f, **style(f))
    ax.set(xlabel="time [s]", ylabel="total error [°]", title=name)
    ax.legend(loc="upper left", ncols=4, fontsize=8)
    return fig


def groups_figure(per_group_total: pd.DataFrame):
    """Bars of mean total RMSE per BROAD group, one bar series per filter of ``MAIN_FILTERS`` found in
    the columns (label = filter name, colour ``report.style.color``); ``None`` when none is."""
    import matplotlib.pyplot as plt

    cols = [f for f in MAIN_FILTERS if f in per_group_total]
    if not cols:
        return None
    g = per_group_total[cols]
    fig, ax = plt.subplots(figsize=(12, 4))
    w = 0.8 / len(cols)
    x = np.arange(len(g))
    for i, f in enumerate(cols):
        ax.bar(x + i * w, g[f].to_numpy(), w, label=f, color=color(f))
    ax.set_xticks(x + 0.4 - w / 2, g.index, rotation=40, ha="right")
    ax.set(ylabel="mean total RMSE [°]", title="BROAD groups (held-out)")
    ax.legend(ncols=len(cols), fontsize=8)
    return fig


def timeline_figure(name: str, trial, timeline: dict, truth_state):
    """The toggling filter's α_acc and predicted state (toggling's style) over the ground-truth
    motion state ``truth_state`` (per-sample class index; the truth's style)."""
    import matplotlib.pyplot as plt

    time_s = np.arange(trial.n_samples) / trial.fs
    fig, (a1, a2) = plt.subplots(2, 1, figsize=(10, 4), sharex=True)
    a1.plot(time_s, timeline["alpha_acc"], label="toggling", **style("toggling"))
    a1.set(ylabel="α_acc", title=name, ylim=(0, None))
    p = timeline["p"]
    pred_state = np.where(np.isnan(p).any(axis=1), -1, np.argmax(np.nan_to_num(p), axis=1))
    a2.plot(time_s, truth_state, label="ground truth", **style("truth"))
    a2.plot(time_s, pred_state, label="predicted (toggling)", **style("toggling"))
    a2.set_yticks(range(len(timeline["states"])), timeline["states"], fontsize=7)
    a2.set(xlabel="time [s]")
    a2.legend(loc="upper right", fontsize=7)
    return fig


def _plots(out: Path, df, per_group_total, series, timelines, trials):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    figures = []
    for name, s in series.items():
        if s:
            figures.append((f"error_{name}.png", lambda name=name, s=s: error_figure(name, trials[name], s)))
    figures.append(("groups.png", lambda: groups_figure(per_group_total)))
    for name, tl in timelines.items():
        figures.append((f"timeline_{name}.png", lambda name=name, tl=tl: timeline_figure(
            name, trials[name], tl, make_targets(trials[name]).state)))
    for fname, make in figures:
        fig = make()
        if fig is not None:
            atomic_write_bytes(out / fname, png_bytes(fig))
            plt.close(fig)
