"""The pretrained learned VQF and its portable file (togglecf.learn.portable, togglecf.toggling.pretrained,
togglecf.run.pretrained): the file reproduces a model directory's filter bit for bit, the same model
gives the same bytes, ``LearnedVQF`` behaves as every filter (update == update_batch, state
save/restore), and the no-harm check and the ship script refuse a recipe that harms."""
import json
import shutil
import subprocess
import sys
import zipfile
from dataclasses import asdict
from pathlib import Path

import numpy as np
import pytest
from conftest import with_fixed_gains

from togglecf.core.io import file_sha256
from togglecf.filters.vqf_core import VQFCoreFilter
from togglecf.filters.vqf_toggling import VQFTogglingSettings
from togglecf.learn.portable import PORTABLE_FORMAT, load_portable
from togglecf.run.pretrained import NO_HARM_MARGIN, dataset_notice, model_card, no_harm_check
from togglecf.toggling import load_toggling_filter
from togglecf.toggling.inloop import ModelVQFTogglingFilter
from togglecf.toggling.pretrained import (PRETRAINED_FILE, LearnedVQF, load_pretrained, portable_from_model_dir,
                                         pretrained_settings)

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def vqf_dir(tiny_model_dir, tmp_path_factory):
    """The tiny models with fixed learned-VQF settings (9D and 6D), τ_acc differing per state and the
    measured back-off on, so that the models visibly steer the filter."""
    d = tmp_path_factory.mktemp("pre") / "m"
    shutil.copytree(tiny_model_dir, d)

    def settings(classes, static, use_mag):
        return VQFTogglingSettings(states=tuple(classes), tau_acc_states=tuple(1.0 + 2.0 * i for i in range(len(classes))),
                                   mag_disturbance_scale=10.0 if use_mag else 0.0, modulation_tau=3.0)
    return with_fixed_gains(d, settings)


@pytest.fixture(scope="module")
def portable(vqf_dir, tmp_path_factory):
    return portable_from_model_dir(vqf_dir, tmp_path_factory.mktemp("npz") / "learned_vqf.npz", {"note": "test"})


def test_portable_file_runs_the_model_directory_filter_bit_for_bit(vqf_dir, portable, mini_trial):
    t = mini_trial
    for use_mag in (True, False):
        ref = load_toggling_filter(vqf_dir, t.fs, use_mag=use_mag, kind="vqf_toggling")
        mine = LearnedVQF(t.fs, use_mag=use_mag, model=portable)
        mag = t.mag if use_mag else None
        a, b = ref.update_batch(t.gyr, t.acc, mag), mine.update_batch(t.gyr, t.acc, mag)
        assert np.array_equal(a.quat, b.quat)
        assert np.array_equal(a.diagnostics["tau_acc"], b.diagnostics["tau_acc"])
        assert np.unique(b.diagnostics["tau_acc"]).size > 2  # the models steer it (not the core alone)
        assert not mine.runs_core_alone and not mine.settings.learning_off(use_mag)
    assert LearnedVQF(t.fs, model=portable).model_metadata == {"note": "test"}


@pytest.fixture(scope="module")
def portable_off(tiny_model_dir, tmp_path_factory):
    """A portable file of the tiny models whose learned settings are the core's in 9D and 6D (learning off)."""
    d = tmp_path_factory.mktemp("pre_off") / "m"
    shutil.copytree(tiny_model_dir, d)
    def settings(classes, static, use_mag):
        return VQFTogglingSettings(states=tuple(classes), confidence_floor=0.3, modulation_tau=2.0)
    with_fixed_gains(d, settings)
    return portable_from_model_dir(d, tmp_path_factory.mktemp("npz_off") / "off.npz", {"note": "off"})


def test_learning_off_needs_every_learned_term_off():
    """``VQFTogglingSettings.learning_off``: per-state values equal to the core's and no learned term
    active; σ_m and w_m count in 9D only; the confidence floor and modulation_tau change nothing then."""
    base = VQFTogglingSettings(states=("a", "b"), confidence_floor=0.5, modulation_tau=3.0)
    assert base.learning_off(True) and base.learning_off(False)
    for field in ("tau_acc_states", "tau_mag_states", "bias_sigma_motion_states", "rest_th_gyr_states",
                  "rest_th_acc_states"):
        vals = getattr(base, field)
        other = VQFTogglingSettings(**{**asdict(base), field: (vals[0], vals[1] * 1.5)})
        assert not other.learning_off(True) and not other.learning_off(False), field
    assert not VQFTogglingSettings(**{**asdict(base), "noise_weight_acc": 0.1}).learning_off(False)
    for mag_term in ({"mag_disturbance_scale": 5.0}, {"noise_weight_mag": 0.5}):
        s = VQFTogglingSettings(**{**asdict(base), **mag_term})
        assert not s.learning_off(True) and s.learning_off(False), mag_term  # 6D ignores the magnetometer
    changed_core = VQFTogglingSettings(states=("a", "b"), tau_acc=5.0)  # per-state values default to the core's
    assert changed_core.learning_off(True)


def test_learned_vqf_with_learning_off_runs_the_core_alone(portable_off, mini_trial):
    """Learning off: ``LearnedVQF`` is ``VQFCoreFilter`` with the core settings, bit for bit (no trees, no
    feature window, the core's diagnostics). The models in the loop with the same settings give the same
    orientation within rounding only: a prediction makes the learned path rebuild the core's
    coefficients from exp(Σ p_s ln τ_s), one ulp off τ. Largest difference measured on real data
    (BROAD 05 and 24, Nexus 5 AR; 9D and 6D): 3.3e-15 per quaternion component, hence 1e-12."""
    t = mini_trial
    for use_mag in (True, False):
        mag = t.mag if use_mag else None
        f = LearnedVQF(t.fs, use_mag=use_mag, model=portable_off)
        assert f.runs_core_alone and isinstance(f.runner, VQFCoreFilter) and f.use_mag == use_mag
        out = f.update_batch(t.gyr, t.acc, mag)
        core = VQFCoreFilter(t.fs, f.settings.core_settings, use_mag=use_mag).update_batch(t.gyr, t.acc, mag)
        assert np.array_equal(out.quat, core.quat) and set(out.diagnostics) == set(core.diagnostics)
        assert "fallback" not in out.diagnostics and f.diagnostic_names == VQFCoreFilter.diagnostic_names
        inloop = ModelVQFTogglingFilter(t.fs, f.settings, models=f.models, use_mag=use_mag).update_batch(t.gyr, t.acc,
                                                                                                         mag)
        assert np.isfinite(inloop.diagnostics["p_" + f.settings.states[0]]).any()  # the trees did predict
        assert np.abs(inloop.quat - out.quat).max() <= 1e-12


def test_learned_vqf_core_alone_update_equals_batch_and_state_restores(portable_off, mini_trial):
    t = mini_trial
    n = 1500
    batch = LearnedVQF(t.fs, model=portable_off).update_batch(t.gyr[:n], t.acc[:n], t.mag[:n]).quat
    f = LearnedVQF(t.fs, model=portable_off)
    assert np.array_equal(np.array([f.update(t.gyr[i], t.acc[i], t.mag[i]) for i in range(n)]), batch)
    assert np.array_equal(f.quat, batch[-1])
    g = LearnedVQF(t.fs, model=portable_off)
    g.update_batch(t.gyr[:700], t.acc[:700], t.mag[:700])
    h = LearnedVQF(t.fs, model=portable_off)
    h.set_state(g.get_state())
    assert np.array_equal(h.update_batch(t.gyr[700:n], t.acc[700:n], t.mag[700:n]).quat, batch[700:])
    h.reset()
    assert np.array_equal(h.update_batch(t.gyr[:n], t.acc[:n], t.mag[:n]).quat, batch)


@pytest.mark.skipif(not PRETRAINED_FILE.is_file(), reason="this checkout ships no pretrained model")
def test_shipped_model_runs_the_core_alone_where_its_settings_learn_nothing():
    for use_mag in (True, False):
        assert LearnedVQF(100.0, use_mag=use_mag).runs_core_alone == pretrained_settings(use_mag).learning_off(use_mag)


def test_same_model_same_bytes_and_numpy_reads_it(vqf_dir, portable, tmp_path):
    again = portable_from_model_dir(vqf_dir, tmp_path / "again.npz", {"note": "test"})
    assert file_sha256(again) == file_sha256(portable)  # fixed zip time stamps: make run can check the shipped file
    with np.load(portable, allow_pickle=False) as z:  # numpy alone opens it
        assert {"feature", "threshold", "value", "feature_low"} <= set(z.files)
    header = json.loads(zipfile.ZipFile(portable).read("header.json"))
    assert header["format"] == PORTABLE_FORMAT and set(header["gains"]) == {"vqf_9d", "vqf_6d"}


def test_portable_header_is_strict_json_where_a_value_is_not_finite(vqf_dir, tmp_path):
    """A re-learning's report can hold an objective of +inf (``mean_dataset_log_ratio`` with a dataset above
    learning off) or NaN: the header stays strict JSON (no ``Infinity``/``NaN`` tokens, which JSON readers
    outside Python refuse), those values null, the rest as given, and the model still loads."""
    path = portable_from_model_dir(vqf_dir, tmp_path / "m.npz",
                                   {"search": {"objective_pretrained": float("inf"), "objective_core": float("nan"),
                                               "objective_search": -0.25}})
    text = zipfile.ZipFile(path).read("header.json").decode()

    def refuse(token):
        raise ValueError(f"not strict JSON: {token}")
    header = json.loads(text, parse_constant=refuse)
    assert header["metadata"]["search"] == {"objective_pretrained": None, "objective_core": None,
                                            "objective_search": -0.25}
    assert load_portable(path).metadata["search"]["objective_search"] == -0.25


def test_portable_refuses_another_format_with_what_to_do(portable, tmp_path):
    bad = tmp_path / "bad.npz"
    with zipfile.ZipFile(portable) as src, zipfile.ZipFile(bad, "w") as dst:
        for name in src.namelist():
            data = src.read(name)
            if name == "header.json":
                h = json.loads(data)
                h["format"] = PORTABLE_FORMAT + 1
                data = json.dumps(h).encode()
            dst.writestr(name, data)
    with pytest.raises(ValueError, match=f"format {PORTABLE_FORMAT + 1}.*reads format {PORTABLE_FORMAT}"):
        load_portable(bad)
    (tmp_path / "junk.npz").write_bytes(b"not a zip")
    with pytest.raises(ValueError, match="not a togglecf model file"):
        load_portable(tmp_path / "junk.npz")


def test_learned_vqf_update_equals_batch_and_state_restores(portable, mini_trial):
    t = mini_trial
    n = 1500
    batch = LearnedVQF(t.fs, model=portable).update_batch(t.gyr[:n], t.acc[:n], t.mag[:n]).quat
    f = LearnedVQF(t.fs, model=portable)
    one = np.array([f.update(t.gyr[i], t.acc[i], t.mag[i]) for i in range(n)])
    assert np.array_equal(one, batch)
    g = LearnedVQF(t.fs, model=portable)
    g.update_batch(t.gyr[:700], t.acc[:700], t.mag[:700])
    h = LearnedVQF(t.fs, model=portable)
    h.set_state(g.get_state())
    assert np.array_equal(h.update_batch(t.gyr[700:n], t.acc[700:n], t.mag[700:n]).quat, batch[700:])


def _lodo(learned, core):
    """A leave-one-dataset-out result (``lodo_json`` form) of two trials with these totals."""
    return {"vqf_toggling": {"a": {"total": learned[0]}, "b": {"total": learned[1]}},
            "vqf_core": {"a": {"total": core[0]}, "b": {"total": core[1]}}}


def test_no_harm_check_allows_the_margin_and_no_more():
    ok = (1.0 + NO_HARM_MARGIN) * 2.0 - 1e-9  # mean 2.0 for VQF, the learned VQF just within the margin
    r = no_harm_check({"x": _lodo((ok, ok), (1.0, 3.0)), "y": _lodo((2.1, 2.1), (1.0, 3.0))})
    assert r["x"]["passed"] and not r["y"]["passed"]  # 2.1 = +5 %
    assert r["y"]["ratio"] == pytest.approx(1.05)


def test_ship_script_refuses_a_recipe_that_harms(vqf_dir, tmp_path):
    src = tmp_path / "reports_pretrained"
    src.mkdir()
    check = no_harm_check({"x": _lodo((2.1, 2.1), (1.0, 3.0))})
    portable_from_model_dir(vqf_dir, src / "learned_vqf.npz", {"no_harm": check})
    (src / "MODEL_CARD.md").write_text("card")
    before = file_sha256(PRETRAINED_FILE) if PRETRAINED_FILE.is_file() else None
    r = subprocess.run([sys.executable, str(ROOT / "pipelines" / "ship_pretrained.py"), "--from", str(src)],
                       capture_output=True, text=True)
    assert r.returncode == 1 and "not shipped: worse than VQF + 2 % on x" in r.stderr and "Traceback" not in r.stderr
    assert (file_sha256(PRETRAINED_FILE) if PRETRAINED_FILE.is_file() else None) == before


def test_model_card_states_data_licences_and_the_check(mini_index):
    notice = dataset_notice(mini_index.root)
    meta = {"recipe": "r", "togglecf": "0", "seed": 1, "classes": ["rest", "rotation"], "training_trials": 3,
            "datasets": [{"name": "broad_mini", "trials": 3, "rates_hz": [285.714], "notice": notice}],
            "settings": {"vqf_9d": {"tau_acc_states": [1.0, 3.0], "tau_acc": 3.0, "confidence_floor": 0.0,
                                    "mag_disturbance_scale": 10.0, "mag_backoff_measured": False,
                                    "mag_rejection_factor": 2.0},
                         "vqf_6d": {"tau_acc_states": [3.0, 3.0], "tau_acc": 3.0, "confidence_floor": 0.0,
                                    "mag_disturbance_scale": 0.0, "mag_backoff_measured": False,
                                    "mag_rejection_factor": 2.0}},
            "no_harm": no_harm_check({"broad_mini": _lodo((2.1, 2.1), (1.0, 3.0))})}
    card = model_card(meta, None, [mini_index.root], "abc")
    assert "| broad_mini | 3 | 285.714 |" in card and "| vqf_9d | 1, 3 | 0 | 10 | at most the core's own rejection factor: the heading gain never below 1/2 of VQF's |" in card
    assert "| vqf_6d | 3, 3 | 0 | 0 | off |" in card
    assert all(f"> {line}" in card for line in notice)
    assert "vqf_6d: every learned value equals VQF's" in card and "vqf_9d: τ_acc per state" in card


#: three real Nexus 5 trials (tyrex_nexus5 beside the repository) for the re-tuning
RETUNE_DATA = ROOT.parent / "shared" / "data" / "tyrex_nexus5"
RETUNE_TRIALS = "Guillaume_Nexus5_Dist_AR,Guillaume_Nexus5_Dist_Texting,Jakob_Nexus5_Dist_Phoning"
#: a short search (a few values per coordinate, one sweep) so that the test takes seconds, not minutes
RETUNE_CONFIG = """[run]
nthread = 1
[gains.vqf]
tau_acc = [2.0, 3.0, 5.0]
confidence_floor = [0.0]
mag_disturbance_scale = [0.0, 10.0]
sweeps = 1
"""


@pytest.fixture(scope="module")
def retuned(tmp_path_factory):
    """``togglecf train --from-pretrained --guard`` on three Nexus 5 trials, run through the command line."""
    if not (RETUNE_DATA / "trials.json").is_file():
        pytest.skip(f"the phone data is not beside the repository ({RETUNE_DATA})")
    if not PRETRAINED_FILE.is_file():
        pytest.skip("this checkout ships no pretrained model")
    from togglecf.cli.main import main
    d = tmp_path_factory.mktemp("retune")
    (d / "small.toml").write_text(RETUNE_CONFIG)
    assert main(["train", "--from-pretrained", "--config", str(d / "small.toml"), "--data", str(RETUNE_DATA),
                 "--trials", RETUNE_TRIALS, "--out", str(d / "out"), "--guard"]) == 0
    return d / "out" / "learned_vqf.npz"


def _searched(retuned: Path) -> Path:
    """The file with the re-learned settings: the guard's file where it kept them, else the unguarded one."""
    unguarded = retuned.parent / "learned_vqf_unguarded.npz"
    return unguarded if unguarded.is_file() else retuned


def test_retune_keeps_the_forest_and_stores_the_searched_settings(retuned):
    from togglecf.toggling.gains import VQFGainSearch
    from togglecf.toggling.pretrained import pretrained_settings
    pre, new, searched = load_portable(PRETRAINED_FILE), load_portable(retuned), load_portable(_searched(retuned))
    for name, a in pre.models.forest.as_arrays().items():  # the models are not retrained
        assert np.array_equal(a, new.models.forest.as_arrays()[name]), name
        assert np.array_equal(a, searched.models.forest.as_arrays()[name]), name
    assert new.models.schema_hash == pre.models.schema_hash
    assert np.array_equal(new.models.feature_low, pre.models.feature_low)
    meta = new.metadata
    assert meta["retuned_from"] == {"file": PRETRAINED_FILE.name, "sha256": file_sha256(PRETRAINED_FILE),
                                    "recipe": pre.metadata.get("recipe")}
    assert meta["retune_trials"] == RETUNE_TRIALS.split(",")
    assert set(meta["search"]) == set(pre.gains) == set(new.gains) == set(meta["guard"])  # 9D and 6D, as shipped
    grid = VQFGainSearch(tau_acc=(2.0, 3.0, 5.0))
    core = json.loads(json.dumps(asdict(grid.start(pre.models.class_names))))
    for mode, rep in meta["search"].items():
        accepted = {p: v for p, v, _ in rep["history"][1:]}  # the coordinates the descent moved, and where to
        s = searched.gains[mode] if rep["kept"] == "search" else None
        if s is not None:  # the stored settings are the descent's end: its accepted steps applied to the core
            start = dict(core)
            for p, v in accepted.items():
                name, _, state = p.partition("[")
                if state:
                    start[name] = list(start[name])
                    start[name][list(pre.models.class_names).index(state[:-1])] = v
                else:
                    start[name] = v
            assert start == s
            assert set(s["tau_acc_states"]) <= {2.0, 3.0, 5.0}  # from the test's grid, not the pretrained's
        else:
            assert searched.gains[mode] == pre.gains[mode]
        # what runs: the searched settings where the guard kept them, else the core's (learning off)
        assert new.gains[mode] == (searched.gains[mode] if meta["guard"][mode]["passed"] else core), mode
        use_mag = mode == "vqf_9d"
        assert LearnedVQF(100.0, use_mag=use_mag, model=retuned).settings == pretrained_settings(use_mag, retuned)
        if not meta["guard"][mode]["passed"]:
            assert LearnedVQF(100.0, use_mag=use_mag, model=retuned).settings.learning_off(use_mag)


def test_retuned_is_not_worse_on_the_objective_it_minimised(retuned):
    """What the search guarantees: the descent only accepts a step that lowers the objective, so it ends at
    or below its start (the core's settings, objective 0 for the log ratio); keeping the better of its end
    and the pretrained settings makes the result at most the pretrained's value too. Recomputed here from
    the stored settings on the same trials, to the float (the same deterministic runs)."""
    from togglecf.data.broad import open_index
    from togglecf.toggling.gains import MODES, objective_value, settings_from_dict, trial_datasets, trial_total_rmse
    from togglecf.filters.vqf_toggling import VQFTogglingSettings
    new = load_portable(_searched(retuned))
    index = open_index([str(RETUNE_DATA)])
    trials = [index.load(n) for n in index.select(RETUNE_TRIALS)]
    preds = [new.models.predict_samples(t.gyr, t.acc, t.mag, t.fs) for t in trials]
    for mode, rep in new.metadata["search"].items():
        hist = [o for _, _, o in rep["history"]]
        assert all(b < a for a, b in zip(hist, hist[1:]))  # each accepted step lowered it
        kept = min(rep["objective_search"], rep["objective_pretrained"])
        assert kept <= rep["objective_core"] and kept <= rep["objective_pretrained"]
        use_mag = MODES[mode][1]
        core = trial_total_rmse(VQFTogglingSettings(states=tuple(new.models.class_names), modulation_tau=3.0),
                                trials, preds, use_mag)
        mine = trial_total_rmse(settings_from_dict(VQFTogglingSettings, new.gains[mode]), trials, preds, use_mag)
        assert objective_value(new.metadata["objective"], mine, core, trial_datasets(trials)) == pytest.approx(
            kept, abs=1e-12)  # the stored settings score what the search reported
        guard = load_portable(retuned).metadata["guard"][mode]
        assert np.allclose(guard["rmse_core"], core, rtol=0, atol=1e-12)  # the guard's core: the same runs


def test_guard_rule_is_the_descents_one_se_step_on_held_out_trials():
    """The guard keeps re-learned settings only when the held-out objective falls by more than one
    standard error of the per-trial change: a consistent 10 % gain passes, the same mean with a
    scatter wider than it does not, a loss never does, fewer than two finite trials never do."""
    from togglecf.run.pretrained import guard_rule
    core = np.array([2.0, 3.0, 4.0, 5.0])
    ds = np.array([""] * 4)
    sure = guard_rule("worst_dataset_log_ratio", core * 0.9, core, ds)
    assert sure["passed"] and sure["n"] == 4
    assert sure["gain"] == pytest.approx(1.001 * np.log(0.9), rel=1e-12)  # the mean log ratio (+ the tie-break)
    assert sure["margin"] == pytest.approx(0.0, abs=1e-12)  # no scatter: one SE is 0
    ratios = np.exp(np.array([-0.5, 0.4, -0.4, 0.1]))  # mean -0.1, one SE 0.21: not beyond its scatter
    assert not guard_rule("worst_dataset_log_ratio", core * ratios, core, ds)["passed"]
    ratios = np.exp(np.array([-0.12, -0.08, -0.11, -0.09]))  # mean -0.1, one SE 0.009: kept
    assert guard_rule("worst_dataset_log_ratio", core * ratios, core, ds)["passed"]
    assert not guard_rule("worst_dataset_log_ratio", core * 1.1, core, ds)["passed"]
    one = guard_rule("worst_dataset_log_ratio", [1.0, np.nan, np.nan, np.nan], core, ds)
    assert not one["passed"] and one["n"] == 1 and "at least 2" in one["reason"]
    assert guard_rule("mean_rmse", core - 0.5, core, ds)["gain"] == pytest.approx(-0.5)  # RMSE objective: in deg


def test_guard_checks_each_fold_on_trials_it_did_not_relearn_on(mini_index, monkeypatch):
    """``relearning_guard`` re-learns on all trials but a fold's and scores that fold: each held-out
    trial's RMSE is that of the settings re-learned without it. The re-learning is replaced by a stub
    that records its trials and returns fixed settings (τ_acc 1 s in every state), so the held-out
    RMSEs are the filter's with those settings, recomputed here."""
    import togglecf.run.pretrained as rp
    from togglecf.toggling.gains import VQFGainSearch, trial_total_rmse
    if not PRETRAINED_FILE.is_file():
        pytest.skip("this checkout ships no pretrained model")
    pm = load_pretrained()
    names = mini_index.select(None)
    trials = [mini_index.load(n) for n in names]
    preds = [pm.models.predict_samples(t.gyr, t.acc, t.mag, t.fs) for t in trials]
    search = VQFGainSearch()
    fixed = VQFTogglingSettings(states=tuple(pm.models.class_names), tau_acc_states=(1.0,) * len(pm.models.class_names),
                                modulation_tau=3.0)
    seen = []

    def stub(tr, pr, pm_, modes, search_, jobs=1, log=None):
        seen.append([t.name for t in tr])
        return {m: asdict(fixed) for m in modes}, {}
    monkeypatch.setattr(rp, "relearn_settings", stub)
    out = rp.relearning_guard(trials, preds, pm, ["vqf_9d"], search, folds=3)["vqf_9d"]
    assert sorted(sum(out["folds"], [])) == sorted(names) and len(out["folds"]) == 3
    for fit, held in zip(seen, out["folds"]):
        assert not set(fit) & set(held) and sorted(fit + held) == sorted(names)
    assert np.allclose(out["rmse_relearned"], trial_total_rmse(fixed, trials, preds, True), rtol=0, atol=1e-12)
    decision = rp.guard_rule(search.objective, out["rmse_relearned"], out["rmse_core"], [""] * len(names))
    assert out["passed"] == decision["passed"] and out["gain"] == pytest.approx(decision["gain"], abs=1e-12)
    few = rp.relearning_guard(trials[:2], preds[:2], pm, ["vqf_9d"], search)["vqf_9d"]
    assert not few["passed"] and "at least 3" in few["reason"]


def test_without_guard_the_file_holds_the_search(retuned, tmp_path):
    """The default (no --guard): the same re-learning, its settings written as they are, no guard in the
    metadata, no second file."""
    from togglecf.cli.main import main
    (tmp_path / "small.toml").write_text(RETUNE_CONFIG)
    assert main(["train", "--from-pretrained", "--config", str(tmp_path / "small.toml"), "--data", str(RETUNE_DATA),
                 "--trials", RETUNE_TRIALS, "--out", str(tmp_path / "out")]) == 0
    plain = load_portable(tmp_path / "out" / "learned_vqf.npz")
    assert plain.metadata["guard"] == {} and not (tmp_path / "out" / "learned_vqf_unguarded.npz").exists()
    assert plain.gains == load_portable(_searched(retuned)).gains  # the same descent, deterministic


def test_guard_only_with_from_pretrained(capsys):
    from togglecf.cli.main import main
    assert main(["train", "--guard"]) != 0
    assert "--guard: only with --from-pretrained" in capsys.readouterr().err


def test_retuned_model_runs_in_evaluate(retuned, capsys):
    from togglecf.cli.main import main
    assert main(["evaluate", "--data", str(RETUNE_DATA), "--trials", RETUNE_TRIALS.split(",")[0], "--jobs", "1",
                 "--models", str(retuned)]) == 0
    captured = capsys.readouterr()
    assert "mean over 1 trials" in captured.out
    assert "used to train" in captured.err  # re-tuned on that trial: its score is flagged as in-sample


def test_retune_searches_the_relearn_table(mini_index, monkeypatch, tmp_path):
    """``train --from-pretrained`` re-learns with ``relearn_search``: ``[gains.relearn]``'s values in place of
    ``[gains.vqf]``'s, the rest as ``[gains.vqf]`` (the re-learning is replaced by a stub that records its search)."""
    import togglecf.run.pretrained as rp
    from togglecf.run.config import load_config
    if not PRETRAINED_FILE.is_file():
        pytest.skip("this checkout ships no pretrained model")

    class Seen(Exception):
        pass

    def stub(tr, pr, pm_, modes, search, jobs=1, log=None):
        raise Seen(search)
    monkeypatch.setattr(rp, "relearn_settings", stub)
    gains = {"vqf": {"tau_acc": [2.0, 4.0], "field_change_scale": [0.0, 5.0]},
             "relearn": {"field_change_scale": [0.0, 7.0]}}
    cfg = load_config({"run": {"nthread": 1}, "gains": gains})
    with pytest.raises(Seen) as seen:
        rp.retune_pretrained(cfg, data_dir=mini_index.root, out=tmp_path, verbose=False)
    search = seen.value.args[0]
    assert search.field_change_scale == (0.0, 7.0) and search.tau_acc == (2.0, 4.0)
