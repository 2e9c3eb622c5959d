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
import json
from pathlib import Path

import numpy as np
from scipy.stats import wilcoxon

from togglecf.core.extras import deferred, require
from togglecf.core.io import atomic_write_bytes, atomic_write_json, atomic_write_text
from togglecf.learn.labels import make_targets
from togglecf.registry import CATALOG
from togglecf.report.style import color, style

pd = deferred("pandas", extra="data", what="writing the study report's tables (togglecf.report.study_report)")

__all__ = ["MAIN_FILTERS", "LABELS", "ABLATION_ROWS", "ABLATION_LABELS", "write_report", "rewrite_summary", "paired_comparison",
           "paired_test", "group_table", "error_figure", "groups_figure", "timeline_figure", "png_bytes"]

MAIN_FILTERS = ("vqf_toggling", "toggling", "vqf", "vqf_core_defaults", "vqf_core", "madgwick", "madgwick_rest_bias",
                "cf", "mahony", "aqua", "ekf")
#: how the study runs each filter it scores, after the filter's label in the table (``CATALOG``)
HOW_RUN = {"vqf_toggling": "(models in the loop)", "toggling": "(models in the loop)", "vqf": "(vqf package, defaults)",
           "vqf_core": "at its fold TAGP (τ_acc × τ_mag)", "madgwick": "(fold TAGP)", "cf": "(fold TAGP)",
           "mahony": "(fold TAGP)", "aqua": "(fold TAGP)", "ekf": "(fold TAGP)"}
#: the study's rows that are not a filter of the table, each a filter run another way
OTHER_ROWS = {"vqf_core_defaults": "VQF core (ours) at VQF's defaults = learning off",
              "madgwick_rest_bias": "Madgwick, initial-rest gyro bias removed (fold TAGP)"}
#: what each row of the study is (summary tables), in ``MAIN_FILTERS`` order
LABELS = {f: OTHER_ROWS[f] if f in OTHER_ROWS else f"{CATALOG[f].label} {HOW_RUN[f]}" for f in MAIN_FILTERS}
#: filters drawn in ``error_<trial>.png`` (back to front) and, in this order, in ``groups.png``
ERROR_PLOT_FILTERS = ("vqf", "madgwick", "cf", "toggling", "vqf_toggling")
#: the bars of the groups figure: the two learned filters, what each is compared with, the fixed CF
GROUP_FIGURE_FILTERS = ("vqf_toggling", "vqf", "toggling", "madgwick", "cf")
ABLATION_ROWS = ("vqf_core_defaults", "vqf_taus_only", "vqf_toggling", "vqf_oracle", "toggling", "toggling_only",
                 "noise_only", "ransac_off", "vqf_toggling_6d", "vqf_core_defaults_6d", "toggling_6d", "cf_6d",
                 "madgwick_6d", "vqf_6d")
#: what each ablation row is
ABLATION_LABELS = {"vqf_core_defaults": "VQF core alone (learning off)",
                   "vqf_taus_only": "VQF core + learned time constants (no noise removal)",
                   "vqf_toggling": "VQF core + learned time constants (the learned filter; noise removal as learned: "
                                   "off by default)",
                   "vqf_oracle": "VQF core + time constants learned and driven by the TRUE motion state (oracle)",
                   "toggling": "toggling CF (the filter; noise removal as learned: off by default)",
                   "toggling_only": "toggling only (η̂ = 0: no noise removal, no predicted-disturbance back-off)",
                   "noise_only": "one gain for all states, no rest bias (noise removal as learned)", "ransac_off": "both, models without RANSAC",
                   "vqf_toggling_6d": "VQF core + learned time constants, 6D (its own 6D gains)",
                   "vqf_core_defaults_6d": "VQF core alone, 6D (learning off)",
                   "toggling_6d": "both, 6D", "cf_6d": "fixed CF, 6D", "madgwick_6d": "Madgwick, 6D", "vqf_6d": "VQF, 6D"}
#: paired per-trial comparisons in the summary: (filter, other)
PAIRS = (("vqf_toggling", "vqf"), ("vqf_toggling", "vqf_core"), ("vqf_toggling", "vqf_core_defaults"),
         ("vqf_toggling", "madgwick"), ("vqf_toggling_6d", "vqf_6d"), ("vqf_toggling_6d", "vqf_core_defaults_6d"),
         ("toggling", "vqf"), ("toggling", "madgwick"))
#: |difference| [deg] of a trial's total RMSE below which the pair counts as a tie on that trial
TIE_DEG = 0.01


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
    datasets = sorted({t.split("/")[0] for t in result["trials"] if "/" in t})  # several: "<dataset>/<trial>"
    where = f"{n} trials of {', '.join(datasets)}" if datasets else f"{n} BROAD trials"
    lines = [f"# Held-out study: toggling CF vs classic filters and VQF ({where}, 9D)", ""]
    lines += ["Every trial is filtered with models and gains trained **without** it "
              f"({len(result['folds'])} folds by whole trial); each baseline runs at its TAGP over the same "
              "training folds; VQF at its defaults. RMSE in degrees over BROAD's movement samples.", ""]
    if result["missing"]:
        lines += [f"Trials not present ({len(result['missing'])} of BROAD's 39): " + ", ".join(result["missing"]), ""]
    mains = [f for f in MAIN_FILTERS if f in wide.columns]
    lines += ["## Mean over all trials", "", "| filter | what | total | heading | inclination | µs/sample (median) |",
              "|---|---|---|---|---|---|"]
    for f in mains:
        sub = df[df["filter"] == f]
        lines.append(f"| {f} | {LABELS.get(f, f)} | {sub['total'].mean():.2f} | {sub['heading'].mean():.2f} | "
                     f"{sub['inclination'].mean():.2f} | {_fmt(speed.get(f, np.nan))} |")
    lines.append("")
    lines += paired_comparison(wide)
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
        desc = ABLATION_LABELS
        for a in abl:
            lines.append(f"| {desc.get(a, a)} | {wide[a].mean():.2f} |")
        lines.append("")
    if "vqf_toggling" in tot:
        cmp = pd.DataFrame(index=tot.index)
        for f in ("vqf_toggling", "vqf_oracle", "vqf", "vqf_core"):
            if f in tot:
                cmp[f] = tot[f]
        for f in ("vqf", "vqf_core"):
            if f in tot:
                cmp[f"Δ {f}"] = tot["vqf_toggling"] - tot[f]
        if "vqf_oracle" in tot:
            cmp["Δ oracle"] = tot["vqf_oracle"] - tot["vqf_toggling"]
        cmp["n_trials"] = tot["n_trials"]
        lines += ["## VQF core + learned time constants vs VQF per BROAD group (total RMSE)", "",
                  "Δ vqf / vqf_core = learned − VQF (package defaults / core at its fold TAGP); Δ oracle = oracle − "
                  "learned (how much a perfect motion-state classifier would change).", "",
                  _md_table(cmp, list(cmp.columns), "group"), ""]
    lines += ["## Folds", ""]
    for fi in result["folds"]:
        tagp = ", ".join(f"{k} {v['params']}" for k, v in fi.get("baseline_tagp", {}).items())
        lines.append(f"- fold {fi['fold']}: test {', '.join(fi['test'])}; models {fi['train_s']:.0f} s, gains "
                     f"{fi['gains_s']:.0f} s; learned gains {fi['gains']}; learned VQF time constants "
                     f"{fi.get('vqf_gains', '-')}; baseline TAGPs: {tagp}")
    lines += ["", f"Total time {result['timing']['total_s']:.0f} s (baseline grids "
              f"{result['timing']['baseline_grids_s']:.0f} s).", ""]
    lines += ["## Per trial (total RMSE)", "", _md_table(wide[[c for c in mains]], mains, "trial"), ""]
    return "\n".join(lines)


def paired_test(diff) -> dict:
    """Paired per-trial comparison from the differences ``diff = a − b`` [°] over trials: wins,
    ties (|Δ| < ``TIE_DEG``) and losses of a, the mean Δ, the two-sided Wilcoxon signed-rank p
    (1 when every Δ is 0), and ``tie``: p ≥ 0.05, no evidence of a difference."""
    d = np.asarray(diff, np.float64)
    wins, losses = int(np.sum(d < -TIE_DEG)), int(np.sum(d > TIE_DEG))
    p = float(wilcoxon(d).pvalue) if np.any(d != 0) else 1.0
    return {"n": len(d), "wins": wins, "ties": len(d) - wins - losses, "losses": losses, "mean": float(np.mean(d)),
            "p": p, "tie": p >= 0.05}


def paired_comparison(wide: pd.DataFrame) -> list[str]:
    """Markdown lines: for each pair of ``PAIRS`` present, per-trial wins/ties/losses of the first
    filter (total RMSE, tie band ``TIE_DEG``), the mean difference and the two-sided Wilcoxon
    signed-rank p over the trials both ran (a p ≥ 0.05 is no evidence of a difference: a tie)."""
    rows = []
    for a, b in PAIRS:
        if a not in wide or b not in wide:
            continue
        both = wide[[a, b]].dropna()
        d = (both[a] - both[b]).to_numpy()
        if len(d) < 2:
            continue
        t = paired_test(d)
        verdict = "tie (p ≥ 0.05)" if t["tie"] else (f"{a} better" if t["mean"] < 0 else f"{b} better")
        rows.append(f"| {a} vs {b} | {t['n']} | {t['wins']} / {t['ties']} / {t['losses']} | {t['mean']:+.2f} | "
                    f"{t['p']:.3g} | {verdict} |")
    if not rows:
        return []
    return ["## Paired per-trial comparison (total RMSE)", "",
            f"Wins / ties / losses of the first filter (tie: |Δ| < {TIE_DEG}°), mean Δ = first − second [°], "
            "two-sided Wilcoxon signed-rank p over the trials.", "",
            "| pair | trials | wins / ties / losses | mean Δ | p | verdict |", "|---|---|---|---|---|---|", *rows, ""]


def rewrite_summary(out) -> Path:
    """Rewrite ``summary.md`` of a finished study in ``out`` from its ``per_trial.csv`` and
    ``results.json`` (after a change of the report, without re-running the study)."""
    out = Path(out)
    df = pd.read_csv(out / "per_trial.csv")
    result = json.loads((out / "results.json").read_text())
    per_group = {m: group_table(df, result["groups"], m) for m in ("total", "heading", "inclination", "roll", "pitch",
                                                                   "yaw", "us_per_sample") if m in df}
    return atomic_write_text(out / "summary.md", _summary(df, per_group, result))


def png_bytes(fig) -> bytes:
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=90, bbox_inches="tight")
    return buf.getvalue()


def error_figure(name: str, trial, series: dict):
    """Total error [deg] over time of the filters of ``ERROR_PLOT_FILTERS`` found in ``series``
    (filter -> per-sample error), each in its ``report.style``; line labels are the filter names."""
    plt = require("matplotlib.pyplot", extra="plot", what="drawing the study report's figures")

    time_s = np.arange(trial.n_samples) / trial.fs
    fig, ax = plt.subplots(figsize=(10, 3.2))
    for f in ERROR_PLOT_FILTERS:
        if f in series:
            ax.plot(time_s, series[f], label=f, **style(f))
    ax.set(xlabel="time [s]", ylabel="total error [°]", title=name)
    ax.legend(loc="upper left", ncols=4, fontsize=8)
    return fig


def groups_figure(per_group_total: pd.DataFrame):
    """Bars of mean total RMSE per BROAD group, one bar series per filter of ``GROUP_FIGURE_FILTERS``
    found in the columns (label = filter name, colour ``report.style.color``), each bar labelled with
    its value (the axis is never clipped); ``None`` when none is. Every row is in ``per_group.csv``."""
    plt = require("matplotlib.pyplot", extra="plot", what="drawing the study report's figures")

    cols = [f for f in GROUP_FIGURE_FILTERS if f in per_group_total]
    if not cols:
        return None
    g = per_group_total[cols]
    fig, ax = plt.subplots(figsize=(12, 4.5))
    w = 0.8 / len(cols)
    x = np.arange(len(g))
    for i, f in enumerate(cols):
        bars = ax.bar(x + i * w, g[f].to_numpy(), w, label=f, color=color(f))
        ax.bar_label(bars, fmt="%.1f", fontsize=6, padding=1)
    ax.set_xticks(x + 0.4 - w / 2, g.index, rotation=30, ha="right")
    ax.set(ylabel="mean total RMSE [°]", title="BROAD groups (held out)")
    ax.set_ylim(0, 1.12 * float(np.nanmax(g.to_numpy())))
    ax.legend(ncols=len(cols), fontsize=8, loc="upper left")
    fig.tight_layout()
    return fig


def timeline_figure(name: str, trial, timeline: dict, truth_state):
    """The toggling filter's α_acc and predicted state (toggling's style) over the ground-truth
    motion state ``truth_state`` (per-sample class index; the truth's style)."""
    plt = require("matplotlib.pyplot", extra="plot", what="drawing the study report's figures")

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
    require("matplotlib", extra="plot", what="drawing the study report's figures").use("Agg")
    plt = require("matplotlib.pyplot", extra="plot", what="drawing the study report's figures")

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
