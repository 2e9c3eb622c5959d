"""``togglecf evaluate`` and ``togglecf tune``: filters on BROAD trials, BROAD's error tables (pandas:
the ``data`` extra), resumable sweeps on the local or a Dask backend (``togglecf.run.sweep``)."""
from __future__ import annotations

import dataclasses
import sys
import time
from pathlib import Path

import numpy as np
import pandas as pd

from togglecf import __version__
from togglecf.cli.common import backend_from_args, backend_settings, data_index
from togglecf.cli.filter_list import filter_names, filter_specs
from togglecf.core.io import atomic_write_json, atomic_write_text
from togglecf.data.broad import MAX_INVALID_FRACTION
from togglecf.metrics.broad import METRICS, group_means
from togglecf.parallel.backend import sweep_chunk_size
from togglecf.registry import LEARNED_VQF, FilterSpec
from togglecf.run.scoring import parse_grid
from togglecf.run.sweep import ResultStore, format_failures, grid_search, journal_path, run_sweep
from togglecf.toggling.load import trained_files_among, training_trials_among
from togglecf.toggling.pretrained import load_pretrained

__all__ = ["cmd_evaluate", "cmd_tune", "settings_json"]


def _params(specs) -> dict:
    grid = parse_grid(specs)
    bad = [k for k, v in grid.items() if len(v) != 1]
    if bad:
        raise ValueError(f"--param {bad[0]} takes one value; use `togglecf tune --grid` for several")
    return {k: v[0] for k, v in grid.items()}


def _tables(results: dict, groups: dict, invalid: dict | None = None):
    invalid = invalid or {}
    per_trial = pd.DataFrame(
        [{"trial": r.trial, **{m: r.errors[m] for m in METRICS}, "us_per_sample": r.us_per_sample,
          "n_samples": r.n_samples, "n_invalid": invalid.get(r.trial, {}).get("samples", np.nan), **r.diagnostics}
         for r in results.values()]).set_index("trial")
    per_group = pd.DataFrame.from_dict(group_means({n: r.errors for n, r in results.items()}, groups),
                                       orient="index")
    per_group.index.name = "group"
    return per_trial, per_group


def _print_tables(title, per_trial, per_group, datasets=()):
    fmt = {c: "{:.3f}".format for c in per_trial.columns if c not in ("n_samples", "n_invalid")}
    if "n_invalid" in per_trial:
        fmt["n_invalid"] = lambda v: "?" if pd.isna(v) else str(int(v))
    print(f"\n{title}\nper trial (RMSE in degrees over the movement samples):")
    print(per_trial.to_string(formatters=fmt))
    what = "group (<dataset>: all its trials; <dataset>/<group>: its trials.json groups)" if datasets else "BROAD group"
    print(f"\nper {what} (mean of the trials present; n_trials of n_listed):")
    print(per_group.to_string(formatters={c: "{:.3f}".format for c in METRICS}))
    print(f"\nmean over {len(per_trial)} trials: total {per_trial['total'].mean():.3f}°, heading "
          f"{per_trial['heading'].mean():.3f}°, inclination {per_trial['inclination'].mean():.3f}°, "
          f"{per_trial['us_per_sample'].median():.3f} µs/sample (median)")
    if "fallback" in per_trial:  # a learned filter: how often its models were not trusted (learn.ranges)
        print(f"fallback (window out of the models' training range): {100 * per_trial['fallback'].mean():.1f} % of "
              f"the scored samples (mean over trials; max {100 * per_trial['fallback'].max():.1f} %)")
    if "low_confidence" in per_trial:  # the toggling CF below its confidence floor: also its fallback gains
        print(f"low confidence (top class probability below the confidence floor): "
              f"{100 * per_trial['low_confidence'].mean():.1f} % of the scored samples (mean over trials; max "
              f"{100 * per_trial['low_confidence'].max():.1f} %)")
    for ds in datasets:  # several data directories: one line per dataset (its group in the table above)
        if ds in per_group.index:
            r = per_group.loc[ds]
            print(f"  {ds}: mean over {int(r['n_trials'])} trials: total {r['total']:.3f}°, heading "
                  f"{r['heading']:.3f}°, inclination {r['inclination']:.3f}°")


def _write(out, per_trial, per_group, meta):
    out = Path(out)
    atomic_write_text(out / "per_trial.csv", per_trial.to_csv(float_format="%.6f"))
    atomic_write_text(out / "per_group.csv", per_group.to_csv(float_format="%.6f"))
    atomic_write_json(out / "results.json", {**meta, "per_trial": per_trial.to_dict(orient="index"),
                                             "per_group": per_group.to_dict(orient="index")})
    print(f"\nwrote {out}/per_trial.csv, per_group.csv, results.json", file=sys.stderr)


def _meta(args, index, names, **extra):
    """results.json's header; ``extra`` (``filter=`` of one of several) overrides."""
    return {"togglecf_version": __version__, "filter": args.filter, "mode": "6D" if args.six_d else "9D",
            "data_dir": _data_dir_meta(index), "trials": names, "missing_trials": index.missing,
            "created_unix": time.time(), **extra}


def settings_json(settings) -> dict:
    """results.json's ``settings``: the settings a filter ran with as a JSON object, ``{"kind": <settings
    class>, "fields": {name: value}}`` (tuples as lists, numpy numbers as numbers), not a Python repr."""
    def plain(v):
        if isinstance(v, dict):
            return {str(k): plain(x) for k, x in v.items()}
        if isinstance(v, (list, tuple, np.ndarray)):
            return [plain(x) for x in v]
        return v.item() if isinstance(v, np.generic) else v
    return {"kind": type(settings).__name__,
            "fields": {f.name: plain(getattr(settings, f.name)) for f in dataclasses.fields(settings)}}


def _data_dir_meta(index):
    """``data_dir`` of results.json: the directory, or the list of them for several."""
    root = index.root
    return [str(r) for r in root] if isinstance(root, (tuple, list)) else str(root)


def cmd_evaluate(args):
    index = data_index(args)
    names = index.select(args.trials)
    specs = _evaluated_specs(args)  # validated (settings, model directories and gains) before any worker starts
    for spec in specs:
        _warn_if_trained_on(spec, index, names)
    with _sweep_context(args) as (backend, store, chunk):
        sweeps = [run_sweep(index, names, spec.name, [spec.as_params()], use_mag=spec.use_mag, backend=backend,
                            store=store, chunk_size=chunk, on_error="report") for spec in specs]
    if args.filters is None:
        return _report_one(args, specs[0], sweeps[0], index, names)
    return _report_several(args, specs, sweeps, index, names)


def _evaluated_specs(args) -> list:
    """``--filter NAME`` (with its ``--param``s) or the filters of ``--filters a,b,c`` (at their defaults)."""
    if args.filters is None:
        return [FilterSpec(args.filter, _params(args.param), models=args.models, use_mag=not args.six_d)]
    if args.param:
        raise ValueError("--param sets one filter's settings: give it with --filter NAME, not with --filters")
    return filter_specs(filter_names(args.filters), args.models, use_mag=not args.six_d)


def _warn_if_trained_on(spec, index, names) -> None:
    """A learned filter scored on trials its models were trained on: one warning line."""
    files = {n: index.available[n] for n in names}
    if spec.name == LEARNED_VQF:  # the shipped model, or a portable file (--models)
        _warn_in_sample(trained_files_among(load_pretrained(spec.models).metadata.get("data_files", {}), files),
                        spec.models or "the pretrained learned VQF", names)
    elif spec.models:
        _warn_in_sample(training_trials_among(spec.models, files), spec.models, names)


def _report_one(args, spec, sweep, index, names) -> int:
    """``--filter``: the per-trial and per-group tables and the mean line; with ``--out`` their files."""
    res = sweep.results[0]
    if not res:
        _print_failure_lines(sweep.failed, index)
        raise ValueError(f"no trial could be evaluated: all {len(names)} selected trial(s) failed (listed above)")
    _report_invalid(sweep.invalid, index)
    per_trial, per_group = _tables(res, index.groups, sweep.invalid)
    settings = spec.settings
    _print_tables(f"{spec.name} ({'6D' if args.six_d else '9D'}) {settings}", per_trial, per_group,
                  getattr(index, "datasets", ()))
    if args.out:
        _write(args.out, per_trial, per_group, _meta(args, index, names, params=spec.as_params(),
                                                      settings=settings_json(settings), failed_trials=sweep.failed,
                                                      invalid_samples=sweep.invalid,
                                                      max_invalid_fraction=MAX_INVALID_FRACTION))
    return _report_failures(sweep.failed, [], index)


def _report_several(args, specs, sweeps, index, names) -> int:
    """``--filters``: one table, a row per filter (``_summary_row``); with ``--out`` each filter's files in
    OUT/<filter>/ (as ``--filter`` writes them) and the table as OUT/summary.csv."""
    rows = {}
    for spec, sweep in zip(specs, sweeps):
        if not sweep.results[0]:
            print(f"{spec.name}: no trial could be evaluated (failures listed below)", file=sys.stderr)
            continue
        per_trial, per_group = _tables(sweep.results[0], index.groups, sweep.invalid)
        rows[spec.name] = _summary_row(per_trial, per_group)
        if args.out:
            _write(Path(args.out) / spec.name, per_trial, per_group, _meta(
                args, index, names, filter=spec.name, params=spec.as_params(), settings=settings_json(spec.settings),
                failed_trials=sweep.failed, invalid_samples=sweep.invalid, max_invalid_fraction=MAX_INVALID_FRACTION))
    _report_invalid(sweeps[0].invalid, index)  # the same samples for every filter
    if rows:
        summary = pd.DataFrame.from_dict(rows, orient="index")
        summary.index.name = "filter"
        _print_summary(summary, args.six_d)
        if args.out:
            atomic_write_text(Path(args.out) / "summary.csv", summary.to_csv(float_format="%.6f"))
            print(f"wrote {args.out}/summary.csv", file=sys.stderr)
    codes = [_report_failures(sweep.failed, [], index, what=f"for {spec.name}") for spec, sweep in zip(specs, sweeps)]
    if not rows:
        raise ValueError(f"no trial could be evaluated by any of the {len(specs)} filters (listed above)")
    return max(codes)


def _summary_row(per_trial, per_group) -> dict:
    """One filter's row of the ``--filters`` table: the means over its trials of BROAD's total, heading and
    inclination RMSE [°], the median µs per sample, and each group's mean total RMSE [°]."""
    row = {"n_trials": len(per_trial), **{m: per_trial[m].mean() for m in ("total", "heading", "inclination")},
           "us_per_sample": per_trial["us_per_sample"].median()}
    return row | {str(g): per_group.loc[g, "total"] for g in per_group.index}


def _print_summary(summary, six_d: bool) -> None:
    fmt = {c: "{:.3f}".format for c in summary.columns if c != "n_trials"}
    print(f"\n{'6D' if six_d else '9D'}: mean RMSE [°] over each filter's trials (total, heading, inclination), "
          "µs per sample (median), then each group's mean total RMSE [°]:")
    print(summary.to_string(formatters=fmt))


def _warn_in_sample(seen, what, names) -> None:
    """One line on stderr when trained models (``what``) are scored on trials they were trained on (``seen``)."""
    if seen:
        shown = ", ".join(seen[:5]) + (f" and {len(seen) - 5} more" if len(seen) > 5 else "")
        print(f"warning: {len(seen)} of the {len(names)} trials scored were used to train {what} ({shown}): "
              "their errors are in-sample, not held out", file=sys.stderr)


def cmd_tune(args):
    index = data_index(args)
    names = index.select(args.trials)
    grid = parse_grid(args.grid)
    FilterSpec(args.filter, {k: v[0] for k, v in grid.items()})  # fail early on a bad name or value
    n = int(np.prod([len(v) for v in grid.values()]))
    print(f"grid of {n} points x {len(names)} trials", file=sys.stderr)
    t0 = time.time()
    with _sweep_context(args) as (backend, store, chunk):
        result = grid_search(index, names, args.filter, grid, use_mag=not args.six_d, backend=backend, store=store,
                             chunk_size=chunk, on_error="report")
    print(f"done in {time.time() - t0:.1f} s ({result.sweep.computed} points computed, {result.sweep.reused} "
          "reused from the journal)", file=sys.stderr)
    per_trial = pd.DataFrame.from_dict(result.per_trial, orient="index")
    per_trial.index.name = "trial"
    per_group = pd.DataFrame.from_dict(group_means(result.per_trial, index.groups), orient="index")
    per_group.index.name = "group"
    curve = ", ".join(f"{v:g}: {e:.3f}" for v, e in zip(next(iter(grid.values())), np.atleast_1d(
        result.mean_total if len(grid) == 1 else [])))
    if curve:
        print(f"\nmean total RMSE over the grid: {curve}")
    print(f"\nTAGP of {args.filter}: {result.params} -> mean total RMSE "
          f"{np.nanmin(result.mean_total):.3f}° over {len(names)} trials")
    per_trial["us_per_sample"] = np.nan
    print(per_group.to_string(formatters={c: "{:.3f}".format for c in METRICS}))
    if args.out:
        _write(args.out, per_trial, per_group, _meta(args, index, names, grid=grid, tagp=result.params,
                                                     mean_total_grid=result.mean_total, failed_trials=result.failed,
                                                     incomplete_trials=result.incomplete))
    return _report_failures(result.failed, result.incomplete, index)


class _sweep_context:
    """Backend (from --backend/--scheduler/--config) and, with --out, the resumable journal."""

    def __init__(self, args):
        self.args = args

    def __enter__(self):
        args = self.args
        settings = backend_settings(args)
        self.backend = backend_from_args(args)
        print(f"backend: {self.backend.describe()}", file=sys.stderr)
        self.store = None
        if args.out:
            self.store = ResultStore(journal_path(args.out), fresh=not args.resume)
            if self.store.done:
                print(f"resuming: {len(self.store.done)} results in {self.store.path} (points already computed "
                      "with the same filter, settings, trial files and version are not computed again)",
                      file=sys.stderr)
        chunk = args.chunk_size if args.chunk_size is not None else settings["chunk_size"]
        return self.backend, self.store, sweep_chunk_size(self.backend, chunk)

    def __exit__(self, *exc):
        if self.store is not None:
            self.store.close()
        self.backend.close()


def _print_failure_lines(failed: dict, index):
    """One line per failed trial on stderr: file, field, problem."""
    for line in format_failures(failed, index.available):
        print(f"  {line}", file=sys.stderr)


def _report_invalid(invalid: dict, index):
    """One stderr line per evaluated trial that holds non-finite IMU samples (the filters skipped them)."""
    for name, c in invalid.items():
        if c.get("samples"):
            per_field = ", ".join(f"{k} {c[k]}" for k in ("gyr", "acc", "mag") if c.get(k))
            n = index.available[name]
            print(f"note: {n}: {c['samples']} IMU sample(s) not finite ({per_field}); the filter skipped them "
                  f"(a trial is refused above {MAX_INVALID_FRACTION:.0%} per field)", file=sys.stderr)


def _report_failures(failed: dict, incomplete: list, index, what: str = "") -> int:
    """Exit code 3 (after writing what was computed) when trials failed; one line per trial on stderr
    (``what``: of which filter, e.g. ``"for vqf"``)."""
    if not failed and not incomplete:
        return 0
    print(f"\nWARNING: {len(failed)} trial(s) failed{' ' + what if what else ''} and are missing from the tables:",
          file=sys.stderr)
    _print_failure_lines(failed, index)
    for name in incomplete:
        if name not in failed:
            print(f"  {index.available.get(name, name)}: not evaluated at every grid point", file=sys.stderr)
    print("rerun with the same --out to compute only the missing points", file=sys.stderr)
    return 3
