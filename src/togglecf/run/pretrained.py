"""The pretrained learned VQF: trained on every dataset present, checked against the leave-one-dataset-out
results of the same recipe, written as one portable file with its model card (``make run`` step 5).

``train_pretrained`` trains (``togglecf train``, the default config, gain modes ``vqf_9d`` and ``vqf_6d``)
on every directory of ``dirs``; ``no_harm_check`` reads the leave-one-dataset-out results (``lodo_json``
of ``run.lodo``, the same recipe in 9D) and says, per dataset left out, whether the learned VQF's mean
total RMSE is at most VQF's (``vqf_core``) + ``NO_HARM_MARGIN``; ``model_card`` writes the card.
``pipelines/ship_pretrained.py`` copies the file and card into the package only when every check passes.
"""
from __future__ import annotations

import datetime as dt
import json
import logging
import time
from dataclasses import asdict
from pathlib import Path

import numpy as np

from togglecf import __version__
from togglecf.core.io import atomic_write_text, file_sha256
from togglecf.core.provenance import source_revision
from togglecf.data.broad import DatasetIndex, open_index
from togglecf.registry import VQF_TOGGLING
from togglecf.run.config import load_config, pretrained_config, relearn_search
from togglecf.run.train import run_training
from togglecf.learn.folds import trial_folds
from togglecf.learn.portable import load_portable, save_portable
from togglecf.filters.vqf_toggling import VQFTogglingSettings
from togglecf.toggling.gains import (
    MODES,
    learn_modes,
    objective_value,
    settings_from_dict,
    step_margin,
    trial_datasets,
    trial_total_rmse,
)
from togglecf.toggling.pretrained import PRETRAINED_FILE, VQF_MODES, load_pretrained, portable_from_model_dir

__all__ = ["NO_HARM_MARGIN", "train_pretrained", "train_pretrained_models", "write_pretrained", "write_model_card",
           "no_harm_check", "model_card", "dataset_notice",
           "retune_pretrained", "relearn_settings", "relearning_guard", "guard_rule", "RETUNED_FILE",
           "UNGUARDED_FILE", "GUARD_FOLDS"]

log = logging.getLogger(__name__)

#: the file ``togglecf train --from-pretrained`` writes in its ``--out`` directory
RETUNED_FILE = "learned_vqf.npz"
#: beside it, when the guard sent a mode back to the core: the re-learned settings it did not keep
UNGUARDED_FILE = "learned_vqf_unguarded.npz"
#: folds by whole trial of the re-learning's guard (``relearning_guard``; ``togglecf train --guard``)
GUARD_FOLDS = 3

#: the pretrained recipe may be at most this much worse (relative) than VQF on a dataset it never saw
NO_HARM_MARGIN = 0.02


def dataset_notice(data_dir) -> list[str]:
    """The citation and licence lines of a dataset: the first block quote of its README.md."""
    readme = Path(data_dir) / "README.md"
    if not readme.is_file():
        return [f"{Path(data_dir).name}: no README.md (no citation or licence known)"]
    lines, seen = [], False
    for line in readme.read_text().splitlines():
        if line.startswith(">"):
            lines.append(line.lstrip("> ").rstrip())
            seen = True
        elif seen:
            break
    return lines or [f"{Path(data_dir).name}: its README.md has no citation block"]


def train_pretrained(dirs, out_dir, lodo: dict | None = None, verbose: bool = True) -> Path:
    """Train on every directory of ``dirs`` into ``out_dir/models``; write ``out_dir/learned_vqf.npz``
    (``learn.portable``) and ``out_dir/MODEL_CARD.md`` (with ``lodo``: the leave-one-dataset-out results).
    Returns the portable file. In two parts: ``train_pretrained_models``, then ``write_pretrained``."""
    train_pretrained_models(dirs, out_dir, verbose)
    return write_pretrained(dirs, out_dir, lodo)


def train_pretrained_models(dirs, out_dir, verbose: bool = True) -> Path:
    """The pretrained recipe's training (``togglecf train``, the default config with ``[gains.pretrained]``'s
    search, ``run.config.pretrained_config``, gain modes ``vqf_9d`` and ``vqf_6d``) on every directory of ``dirs``
    into ``out_dir/models``, which it returns: a task of its own (``make run`` trains it beside the left-out
    datasets, whose results only its card needs)."""
    cfg = pretrained_config(load_config())
    cfg["gains"]["modes"] = ["vqf_9d", "vqf_6d"]
    model_dir = Path(out_dir) / "models"
    run_training(cfg, data_dir=[str(d) for d in dirs], out=model_dir, verbose=verbose)
    return model_dir


def write_pretrained(dirs, out_dir, lodo: dict | None = None) -> Path:
    """``out_dir/learned_vqf.npz`` and its ``MODEL_CARD.md`` from the models ``train_pretrained_models``
    wrote in ``out_dir/models`` (``lodo``: the leave-one-dataset-out results, for the card's check)."""
    out_dir = Path(out_dir)
    model_dir = out_dir / "models"
    meta = json.loads((model_dir / "metadata.json").read_text())
    gains = json.loads((model_dir / "gains.json").read_text())
    datasets = []
    for d in dirs:
        index = DatasetIndex.from_dir(d)
        names = index.select(None)
        rates = sorted({round(float(index.load(n).fs), 3) for n in names})
        datasets.append({"name": Path(d).name, "trials": len(names), "rates_hz": rates, "notice": dataset_notice(d)})
    metadata = {
        "recipe": "togglecf train, the default config with its [gains.pretrained] search, gain modes vqf_9d and vqf_6d",
        "togglecf": __version__, "seed": meta.get("seed"),
        "datasets": datasets, "classes": meta["classes"],
        "training_trials": len(meta["training_trials"]),
        "data_files": meta["data_files"],  # trial -> file name and sha256: evaluate flags in-sample scores
        "settings": {m: gains[m]["settings"] for m in ("vqf_9d", "vqf_6d") if m in gains},
        "no_harm": no_harm_check(lodo) if lodo else {},
    }
    path = portable_from_model_dir(model_dir, out_dir / "learned_vqf.npz", metadata)  # no commit, no date: same
    write_model_card(out_dir, lodo, dirs)  # bytes for the same model
    return path


def write_model_card(out_dir, lodo: dict | None, dirs) -> Path:
    """``out_dir/MODEL_CARD.md`` for the portable ``out_dir/learned_vqf.npz`` (its metadata)."""
    path = Path(out_dir) / "learned_vqf.npz"
    meta = load_portable(path).metadata
    return atomic_write_text(Path(out_dir) / "MODEL_CARD.md", model_card(meta, lodo, dirs, file_sha256(path)))


def _what_it_changes(mode: str, s: dict) -> str:
    """One sentence: how the learned settings of ``mode`` differ from VQF's (the core's) own."""
    use_mag = MODES[mode][1]
    if settings_from_dict(VQFTogglingSettings, s).learning_off(use_mag):
        return f"{mode}: every learned value equals VQF's: this mode runs VQF itself."
    same_tau = all(v == s["tau_acc"] for v in s["tau_acc_states"])
    backoff = s["mag_disturbance_scale"] > 0 and use_mag
    if same_tau and backoff:
        return (f"{mode}: τ_acc stays VQF's {s['tau_acc']:g} s in every state; what the models change is the heading "
                f"back-off (σ_m {s['mag_disturbance_scale']:g} µT, {_backoff_law(s)}).")
    if same_tau:
        return (f"{mode}: τ_acc stays VQF's {s['tau_acc']:g} s in every state; the models change the other settings "
                "above.")
    return f"{mode}: τ_acc per state as above, against VQF's {s['tau_acc']:g} s."


def _backoff_law(s: dict) -> str:
    """The heading back-off's law in words (``VQFTogglingSettings.mag_backoff_measured``)."""
    if s.get("mag_backoff_measured", False):
        return "on at most the deviation the magnetometer shows"
    return (f"at most the core's own rejection factor: the heading gain never below 1/{s.get('mag_rejection_factor', 2.0):g} "
            "of VQF's")


def no_harm_check(lodo: dict) -> dict:
    """Per dataset left out (``lodo_json`` form): the learned VQF's and VQF's mean total RMSE [°], their
    ratio and ``passed`` (ratio <= 1 + ``NO_HARM_MARGIN``)."""
    out = {}
    for ds, per in lodo.items():
        names = sorted(per[VQF_TOGGLING])
        learned = float(np.mean([per[VQF_TOGGLING][n]["total"] for n in names]))
        core = float(np.mean([per["vqf_core"][n]["total"] for n in names]))
        out[ds] = {"trials": len(names), "learned_vqf": learned, "vqf": core, "ratio": learned / core,
                   "passed": learned <= (1.0 + NO_HARM_MARGIN) * core}
    return out


def _worst_groups(lodo: dict, dirs) -> list[str]:
    """Per dataset left out, the group where the learned VQF is worst against VQF (relative mean)."""
    by_name = {Path(d).name: Path(d) for d in dirs}
    lines = []
    for ds, per in lodo.items():
        if ds not in by_name:
            continue
        index = DatasetIndex.from_dir(by_name[ds])
        worst = None
        for g, members in sorted(index.groups.items()):
            m = [n for n in members if n in per[VQF_TOGGLING]]
            if not m:
                continue
            r = np.mean([per[VQF_TOGGLING][n]["total"] for n in m]) / np.mean([per["vqf_core"][n]["total"] for n in m])
            if worst is None or r > worst[1]:
                worst = (g, float(r), len(m))
        if worst:
            lines.append(f"| {ds} | {worst[0]} ({worst[2]} trials) | {100 * (worst[1] - 1):+.1f} % |")
    return lines


def model_card(metadata: dict, lodo: dict | None, dirs, sha256: str) -> str:
    """The model card (Markdown) of a pretrained learned VQF from its metadata and the leave-one-dataset-out
    results of the same recipe."""
    when = f"{dt.datetime.now(dt.timezone.utc):%Y-%m-%d %H:%M} UTC at {source_revision()}"
    ds = metadata["datasets"]
    lines = ["# Model card: the pretrained learned VQF (`togglecf.LearnedVQF`)", "",
             f"*Generated by `python pipelines/main.py` (step 5) on {when}. "
             "Do not edit: rerun the command.* File `learned_vqf.npz`, sha256 `" + sha256 + "`.", "",
             "## What it is", "",
             "The VQF core (`togglecf.filters.vqf_core`) with XGBoost models compiled into its loop "
             "(`togglecf.filters.vqf_toggling`): a motion-state classifier that can set its time constants per "
             "sample, and a regressor of the magnetic disturbance that can slow its heading correction; *Learned "
             "settings* below says what this model changes. 9D "
             "(`LearnedVQF(rate)`) and 6D (`LearnedVQF(rate, use_mag=False)`). Inputs gyr [rad/s], acc [m/s²], "
             "mag [µT] at any rate: the features and settings are set in seconds.", "",
             f"Recipe: {metadata['recipe']} (seed {metadata['seed']}); togglecf {metadata['togglecf']}.", "",
             "## Training data", "", "| dataset | trials | rate [Hz] |", "|---|---|---|"]
    lines += [f"| {d['name']} | {d['trials']} | {', '.join(f'{r:g}' for r in d['rates_hz'])} |" for d in ds]
    lines += ["", f"{metadata['training_trials']} trials in all; motion states: {', '.join(metadata['classes'])}.", "",
              "## Learned settings", "", "| mode | τ_acc per state [s] | c₀ | σ_m [µT] | heading back-off |",
              "|---|---|---|---|---|"]
    for mode, s in metadata["settings"].items():
        lines.append(f"| {mode} | {', '.join(f'{v:g}' for v in s['tau_acc_states'])} | {s['confidence_floor']:g} | "
                     f"{s['mag_disturbance_scale']:g} | {_backoff_law(s) if s['mag_disturbance_scale'] > 0 else 'off'} |")
    lines += ["", *[f"- {_what_it_changes(m, s)}" for m, s in metadata["settings"].items()],
              "", "Everything else is VQF's default (τ_mag 9 s, rest thresholds 2 °/s and 0.5 m/s², no noise "
              "vector subtracted): what does not travel between sensors is not learned "
              "(docs/concepts/vqf-core.md, *Why the learning does no harm off its training data*).", ""]
    if lodo:
        lines += ["## On data it never saw: leave one dataset out", "",
                  "The same recipe (9D) trained on every dataset but one, scored on the one left out "
                  "(`reports/lodo/lodo.md` of the same run). Mean total RMSE [°], BROAD's metric. The model "
                  f"ships only when the learned VQF is at most VQF's error + {100 * NO_HARM_MARGIN:g} % on each.", "",
                  "| left out | trials | learned VQF | VQF | change | passed |", "|---|---|---|---|---|---|"]
        for name, c in metadata["no_harm"].items():
            lines.append(f"| {name} | {c['trials']} | {c['learned_vqf']:.2f} | {c['vqf']:.2f} | "
                         f"{100 * (c['ratio'] - 1):+.1f} % | {'yes' if c['passed'] else '**no**'} |")
        lines += ["", "Where it is worst against VQF (the group of each dataset left out with the largest relative "
                  "change of the mean):", "", "| left out | group | change |", "|---|---|---|", *_worst_groups(lodo, dirs),
                  ""]
    lines += ["## Known limits", "",
              "- Trained at 100 Hz and 285.7 Hz, on one research IMU and two smartphones; other rates and sensors "
              "are covered by the leave-one-dataset-out check above only as far as those three differ.",
              "- 6D was not scored leaving datasets out (the harm looked for was in the heading); its settings "
              "come from the same search.",
              "- The heading needs a magnetometer in µT, and nothing checks the magnetometer's unit: convert first "
              "(`togglecf stream --units` does; a trial file must hold µT).",
              "- Where the models never saw data like the input (a window outside the training ranges) the filter "
              "falls back to VQF's own settings.", "",
              "## Licences of the training data", ""]
    for d in ds:
        lines += [f"**{d['name']}**:", "", *[f"> {line}" for line in d["notice"]], ""]
    lines += ["The package's code is MIT. The model was computed from the data above; keep these notices with it."]
    return "\n".join(lines) + "\n"


def retune_pretrained(config=None, data_dir=None, trials=None, out=None, model=None, verbose: bool = True,
                      modes=None, guard_folds: int = 0) -> dict:
    """``togglecf train --from-pretrained``: re-learn only the learned VQF's settings (9D and 6D, the
    modes the pretrained model has) on the selected trials, keeping the pretrained forest as it is.

    The pretrained models (``model``: a portable file, default the one the package ships) are not
    retrained: they predict on the user's trials, which they never saw, so their predictions are
    already out-of-sample and no cross-validation is needed (``togglecf train`` cross-validates only to
    get such predictions for its own training trials). On them the settings are learned by the same
    coordinate descent as ``togglecf train`` (``gains.learn_modes``, the config's ``[gains.vqf]``
    grids, objective and sweeps with ``[gains.relearn]``'s in their place: ``run.config.relearn_search``, by
    default σ_f, the back-off on the field's change, searched too; ``[run] nthread`` processes), which starts at
    the VQF core's own settings. The descent is greedy, so it may end above the pretrained settings on these trials;
    each mode keeps whichever of the two scores lower on the descent's objective (``kept``), so on
    these trials the result is never worse than the pretrained model, nor than the core.

    That is in-sample. With ``guard_folds`` (``--guard``: ``GUARD_FOLDS``; 0, the default: no guard) the
    guard (``relearning_guard``) checks the re-learning on recordings it did not see: a mode keeps its
    re-learned settings only when they beat the core there by more than one standard error, else it
    runs the VQF core (``guard_rule``). The check re-learns on fewer recordings than the result, so it
    is pessimistic where more recordings still help.

    Writes ``out/learned_vqf.npz`` (``learn.portable``, the format of the shipped model; ``out``
    default ``models/<run.name>-retuned``) with metadata naming the model it was re-tuned from, the
    trials and the guard's decision; where the guard sent a mode back to the core, the re-learned
    settings also go to ``out/learned_vqf_unguarded.npz`` (``UNGUARDED_FILE``). ``modes``: the modes to
    re-learn (default: every one the model has; the others keep the model's settings). Returns
    ``{"path", "unguarded_path" (None when the guard changed nothing), "modes": {mode: objectives, kept,
    history}, "guard": {mode: decision}, "timing_s", "trials"}``."""
    t_start = time.perf_counter()
    cfg = load_config(config)
    run = cfg["run"]
    index = open_index(data_dir if data_dir else (run["data"] or None))
    spec = trials if trials is not None else (None if run["trials"] in ("all", "", None) else run["trials"])
    names = index.select(spec)
    if not names:
        raise ValueError("togglecf train --from-pretrained: no trial selected")
    source_path = Path(model) if model is not None else PRETRAINED_FILE
    pm = load_pretrained(source_path)
    modes = [m for m in VQF_MODES if m in pm.gains and (modes is None or m in modes)]
    if not modes:
        raise ValueError(f"{source_path.name} has no settings of the modes to re-learn ({', '.join(VQF_MODES)})")
    out_dir = Path(out) if out else Path("models") / f"{run['name']}-retuned"
    say = log.info if verbose else (lambda msg: None)
    say(f"togglecf train --from-pretrained: {len(names)} trials, the models of {source_path.name} kept; "
        f"re-learning {', '.join(modes)} -> {out_dir / RETUNED_FILE}")
    loaded = [index.load(n) for n in names]
    t0 = time.perf_counter()
    preds = [pm.models.predict_samples(t.gyr, t.acc, t.mag, t.fs) for t in loaded]
    timing = {"predictions_s": time.perf_counter() - t0}
    search = relearn_search(cfg)
    jobs = int(run["nthread"])
    t0 = time.perf_counter()
    relearned, report = relearn_settings(loaded, preds, pm, modes, search, jobs=jobs, log=say)
    timing["gains_s"] = time.perf_counter() - t0
    guard = {}
    if guard_folds:
        t0 = time.perf_counter()
        guard = relearning_guard(loaded, preds, pm, modes, search, folds=guard_folds, jobs=jobs, log=say)
        timing["guard_s"] = time.perf_counter() - t0
    core = asdict(search.start(pm.models.class_names))
    kept = {m: core if m in guard and not guard[m]["passed"] else relearned[m] for m in modes}
    metadata = _retune_metadata(index, names, source_path, pm, search, report, guard, kept)
    path = save_portable(out_dir / RETUNED_FILE, pm.models, {**pm.gains, **kept}, metadata)
    unguarded = None
    if kept != {m: relearned[m] for m in modes}:  # the guard sent a mode back: its re-learned settings, for the record
        unguarded = save_portable(out_dir / UNGUARDED_FILE, pm.models, {**pm.gains, **relearned},
                                  {**metadata, "recipe": metadata["recipe"] + "; this file: the re-learned settings "
                                   "the guard did not keep", "settings": relearned})
        say(f"the re-learned settings the guard did not keep: {unguarded} (runs as --models FILE too)")
    timing["total_s"] = time.perf_counter() - t_start
    say(f"wrote {path} in {timing['total_s']:.1f} s (predictions {timing['predictions_s']:.1f} s, "
        f"gains {timing['gains_s']:.1f} s" + (f", guard {timing['guard_s']:.1f} s)" if guard else ")"))
    return {"path": path, "unguarded_path": unguarded, "modes": report, "guard": guard, "timing_s": timing,
            "trials": names}


def _retune_metadata(index, names, source_path, pm, search, report: dict, guard: dict, kept: dict) -> dict:
    """The metadata of a re-tuned model file: its recipe, the model it was re-tuned from, the trials and
    their files, the search's report, the guard's decision and the settings ``kept``."""
    data_files = {n: {"file": Path(index.available[n]).name, "sha256": file_sha256(index.available[n])} for n in names}
    return {
        "recipe": "togglecf train --from-pretrained: the pretrained models kept, the learned VQF's settings "
                  "re-learned on the trials below by the gain search of togglecf train ([gains.vqf] with "
                  "[gains.relearn] in its place)"
                  + (", kept where the guard passed, else the VQF core's" if guard else " (no guard)"),
        "togglecf": __version__,
        "retuned_from": {"file": source_path.name, "sha256": file_sha256(source_path),
                         "recipe": pm.metadata.get("recipe")},
        "retune_trials": names,
        "data_dir": [str(r) for r in index.root] if isinstance(index.root, (tuple, list)) else str(index.root),
        "predictions": "the pretrained models' out-of-sample", "objective": search.objective, "search": report,
        "guard": guard,
        "classes": list(pm.models.class_names),
        # the forest's training files and the re-tuning's: evaluate flags scores on either as in-sample
        "data_files": {**pm.metadata.get("data_files", {}), **{f"retuned:{n}": v for n, v in data_files.items()}},
        "settings": kept,
    }


def relearn_settings(trials, predictions, pm, modes, search, jobs: int = 1, log=None) -> tuple[dict, dict]:
    """The re-learning of ``retune_pretrained`` on ``trials`` (``predictions``: the pretrained models'
    ``pm`` on them): per mode of ``modes``, the descent of ``gains.learn_modes`` (``search``: a
    ``VQFGainSearch``) and the better of its end and the pretrained settings (``_keep_better``).
    Returns ``({mode: settings dict}, {mode: objectives, kept, history})``."""
    say = log or (lambda msg: None)
    settings_out, report = {}, {}
    for mode, settings, hist, _ in learn_modes(trials, predictions, pm.models, modes, vqf_search=search, jobs=jobs,
                                               log=say, source="the pretrained models' out-of-sample"):
        report[mode] = _keep_better(mode, settings, hist, pm, trials, predictions, search)
        settings_out[mode] = asdict(settings) if report[mode]["kept"] == "search" else pm.gains[mode]
        say(f"{mode}: kept the {report[mode]['kept']}'s settings ({search.objective}: search "
            f"{report[mode]['objective_search']:.4f}, pretrained {report[mode]['objective_pretrained']:.4f}, "
            f"core {report[mode]['objective_core']:.4f})")
    return settings_out, report


def relearning_guard(trials, predictions, pm, modes, search, folds: int = GUARD_FOLDS, jobs: int = 1,
                     log=None) -> dict:
    """Does re-learning pay on recordings it did not see? ``folds`` test sets by whole trial over
    ``trials`` (``learn.folds.trial_folds``, at most one per trial); for each, the settings re-learned
    (``relearn_settings``) on the other trials score the held-out ones, beside the VQF core
    (``search.start``). ``guard_rule`` decides per mode from the held-out trials' total RMSEs.
    Fewer than 3 trials: no check possible (a fold must re-learn on 2), the mode is not kept.
    Returns ``{mode: {"passed", "gain", "margin", "n", "folds", "rmse_relearned", "rmse_core", "reason"}}``
    (RMSEs [deg] per trial in the order of ``trials``)."""
    say = log or (lambda msg: None)
    names = [t.name for t in trials]
    if len(trials) < 3:
        reason = f"{len(trials)} recordings: the guard needs at least 3 (2 to re-learn on, 1 to check)"
        say(f"guard: {reason}; the VQF core kept")
        return {m: {"passed": False, "reason": reason, "n": 0, "folds": []} for m in modes}
    inner = trial_folds(names, min(int(folds), len(names)))
    start = search.start(pm.models.class_names)
    rmse = {m: np.full(len(trials), np.nan) for m in modes}
    for j, test in enumerate(inner):
        fit = [i for i, n in enumerate(names) if n not in test]
        held = [i for i, n in enumerate(names) if n in test]
        got, _ = relearn_settings([trials[i] for i in fit], [predictions[i] for i in fit], pm, modes, search, jobs)
        for m in modes:
            rmse[m][held] = trial_total_rmse(settings_from_dict(VQFTogglingSettings, got[m]),
                                             [trials[i] for i in held], [predictions[i] for i in held], MODES[m][1])
        say(f"guard: fold {j + 1}/{len(inner)} re-learned on {len(fit)} trials, checked on {len(held)}")
    out = {}
    for m in modes:
        core = trial_total_rmse(start, trials, predictions, MODES[m][1])
        out[m] = {**guard_rule(search.objective, rmse[m], core, trial_datasets(trials)), "folds": inner,
                  "rmse_relearned": rmse[m].tolist(), "rmse_core": core.tolist()}
        say(f"guard {m}: re-learned vs core on the held-out trials {out[m]['gain']:+.4f} ({search.objective}), "
            f"one SE {out[m]['margin']:.4f}: " + ("kept" if out[m]["passed"] else "not kept, the VQF core runs"))
    return out


def guard_rule(objective: str, rmse, core_rmse, datasets) -> dict:
    """The guard's decision from held-out per-trial total RMSEs [deg] of the re-learned settings
    (``rmse``) and of the core (``core_rmse``): ``gain``, the change of the descent's ``objective``
    from the core to the re-learned settings, must be below minus ``margin``, one standard error of
    its per-trial change (``gains.step_margin``, the rule by which the descent takes a step), on at
    least 2 trials with a finite RMSE. Returns ``{"passed", "gain", "margin", "n", "reason"}``."""
    rmse, core_rmse = np.asarray(rmse, np.float64), np.asarray(core_rmse, np.float64)
    datasets = np.asarray(datasets)
    ok = np.isfinite(rmse) & np.isfinite(core_rmse) & (core_rmse > 0) & (rmse > 0)
    n = int(ok.sum())
    if n < 2:
        return {"passed": False, "gain": float("nan"), "margin": float("nan"), "n": n,
                "reason": f"{n} held-out trials with a finite error: at least 2 needed"}
    rmse, core_rmse, datasets = rmse[ok], core_rmse[ok], datasets[ok]
    gain = objective_value(objective, rmse, core_rmse, datasets) - objective_value(objective, core_rmse, core_rmse,
                                                                                   datasets)
    margin = step_margin("one_se", objective, rmse, core_rmse, datasets)
    passed = bool(gain < -margin)
    return {"passed": passed, "gain": float(gain), "margin": float(margin), "n": n,
            "reason": "beat the core by more than one SE" if passed else "not better than the core by one SE"}


def _keep_better(mode, settings, hist, pm, trials, preds, search) -> dict:
    """The descent's result against the pretrained settings of ``mode`` on the descent's objective
    (per-trial ratios to the core's RMSE, the descent's start): which one is kept and both values."""
    use_mag = MODES[mode][1]
    pre = settings_from_dict(type(settings), pm.gains[mode])
    start = search.start(pm.models.class_names)
    rmse_core = trial_total_rmse(start, trials, preds, use_mag)
    obj_pre = objective_value(search.objective, trial_total_rmse(pre, trials, preds, use_mag), rmse_core,
                              trial_datasets(trials))
    obj_search = float(hist[-1][2])
    return {"objective_core": float(hist[0][2]), "objective_search": obj_search, "objective_pretrained": obj_pre,
            "kept": "search" if obj_search <= obj_pre else "pretrained",
            "history": [[p, v, float(o)] for p, v, o in hist]}
