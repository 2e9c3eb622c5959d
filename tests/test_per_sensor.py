"""Your sensor, measured (togglecf.run.per_sensor, pipelines/per_sensor.py): folds within one dataset,
VQF tuned on the same recordings, the learned VQF re-learned and trained from scratch on them."""
import json
import sys
from pathlib import Path

import numpy as np
import pytest

from togglecf.learn.folds import trial_folds
from togglecf.registry import FilterSpec
from togglecf.run.config import load_config
from togglecf.run.per_sensor import (FIELD_CHANGE_GRID, HALF, ROWS, PerSensorConfig, per_sensor, per_sensor_json,
                                     per_sensor_table, training_subsets)
from togglecf.run.scoring import score_trial
from togglecf.run.train import run_training
from togglecf.toggling.gains import VQFGainSearch

PIPELINES = Path(__file__).resolve().parents[1] / "pipelines"
#: a small τ_acc × τ_mag grid [s] with VQF's defaults (3, 9) on it
GRID = {"tau_acc": [1.0, 3.0], "tau_mag": [9.0, 30.0]}
#: tiny models; every learned VQF value at the core's: learning off, whatever the models predict
TINY_LEARNING_OFF = {
    "run": {"cv_folds": 2},
    "classifier": {"n_estimators": 8, "max_depth": 3},
    "regressor": {"n_estimators": 4, "max_depth": 3},
}
VQF_OFF = {"tau_acc": [3.0], "tau_mag": [9.0], "confidence_floor": [0.0], "mag_disturbance_scale": [0.0]}


def test_training_subsets_are_nested_seeded_and_refuse_one():
    train = [f"t{i:02d}" for i in range(10)]
    a = training_subsets(train, (2, 4, 8, 0), seed=3)
    assert set(a) == {2, 4, 8, 0} and a[0] == a[0] and len(a[0]) == 10 and sorted(a[0]) == train
    assert a[2] == a[4][:2] and a[4] == a[8][:4] and a[8] == a[0][:8]  # nested: each the start of the next
    assert training_subsets(train, (2, 4), seed=3) == {2: a[2], 4: a[4]}  # the same shuffle for a seed
    assert training_subsets(train, (4,), seed=4)[4] != a[4]  # another seed, another draw (10 choose 4 orders)
    assert set(training_subsets(train[:3], (2, 8))) == {2, 0}  # 8 of 3: all of them
    with pytest.raises(ValueError, match="at least 2"):
        training_subsets(train, (1,))


def test_vqf_grid_keeps_the_defaults_on_the_grid():
    grid = PerSensorConfig(grid={"tau_acc": [1.0, 6.0], "tau_mag": [5.0]}).vqf_grid()
    assert grid == {"tau_acc": [1.0, 3.0, 6.0], "tau_mag": [5.0, 9.0]}


@pytest.fixture(scope="module")
def learning_off(mini_index, tmp_path_factory):
    """The protocol on the mini trials (one dataset, 3 folds of one trial, 2 training recordings) with
    every learned VQF value at the core's, from a base trained with learning off."""
    tmp = tmp_path_factory.mktemp("per_sensor")
    cfg = load_config()
    for section, values in TINY_LEARNING_OFF.items():
        cfg[section].update(values)
    cfg["gains"]["modes"] = ["vqf_9d"]
    cfg["gains"]["vqf"] = {**cfg["gains"]["vqf"], **VQF_OFF}
    cfg["gains"]["relearn"] = {"field_change_scale": [0.0]}  # the re-learning's σ_f too
    base = tmp / "base"
    run_training(cfg, data_dir=mini_index.root, out=base, verbose=False)
    settings = PerSensorConfig(folds=3, sizes=(2,), scratch_sizes=(2,), grid=GRID)
    results = per_sensor([mini_index.root], tmp / "out", {Path(mini_index.root).name: base}, settings, config=cfg,
                         jobs=1)
    return results[Path(mini_index.root).name], settings


@pytest.mark.slow
def test_learning_off_is_vqf_and_tuning_sees_only_the_training_recordings(learning_off, mini_index):
    plan, settings = learning_off
    names = mini_index.select(None)
    assert plan["folds"] == trial_folds(names, 3, 0)
    rows = plan["sizes"][0]  # 2 of 2 training recordings: all of them
    assert set(rows) == set(ROWS) and all(sorted(rows[r]) == sorted(names) for r in ROWS)
    assert plan["guard_kept"] == {0: [False, False, False]}  # 2 training recordings: too few for the guard
    for n in names:  # learning off: the learned VQF is its core at VQF's defaults, re-learned or from scratch
        for r in ("relearned", "guarded", "scratch"):
            assert abs(rows[r][n]["total"] - rows["vqf_defaults"][n]["total"]) < 1e-6, (r, n)
    # VQF's defaults scored directly; the tuned pair of each fold is the grid's best on its training trials alone
    for k, test in enumerate(plan["folds"]):
        train = [n for n in names if n not in test]
        by_point = {(a, m): np.mean([score_trial(mini_index.load(n), FilterSpec("vqf_core", {"tau_acc": a,
                                                                                            "tau_mag": m}))[0]
                                     .errors["total"] for n in train])
                    for a in GRID["tau_acc"] for m in GRID["tau_mag"]}
        best = min(by_point, key=by_point.get)
        assert plan["tuned"][0][k] == {"tau_acc": best[0], "tau_mag": best[1]}
        for n in test:
            tuned = score_trial(mini_index.load(n), FilterSpec("vqf_core", dict(zip(GRID, best))))[0]
            assert rows["vqf_tuned"][n]["total"] == pytest.approx(tuned.errors["total"], abs=1e-9)
            default = score_trial(mini_index.load(n), FilterSpec("vqf_core"))[0]
            assert rows["vqf_defaults"][n]["total"] == pytest.approx(default.errors["total"], abs=1e-9)


@pytest.mark.slow
def test_table_and_json(learning_off, mini_index):
    plan, _ = learning_off
    name = Path(mini_index.root).name
    text = per_sensor_table({name: plan}, [mini_index.root], "python pipelines/per_sensor.py --x")
    assert text.startswith("*Generated by `python pipelines/per_sensor.py --x`")
    line = next(ln for ln in text.splitlines() if ln.startswith("| all |"))
    cells = [c.strip() for c in line.split("|")[1:-1]]
    assert cells[6] == "0/3"  # the guard kept nothing (2 recordings)
    assert all(cells[i] == cells[1] for i in (3, 4, 5))  # the learned rows' means: VQF's defaults (learning off)
    for i in (7, 10, 13):  # re-learned, guarded and scratch against VQF's defaults: three ties each
        assert cells[i].startswith("+0.0 % · 0/3/0"), (i, cells[i])
    # last: the tuned pair's worst group against VQF's defaults, recomputed from the trials' totals
    rows, groups = plan["sizes"][0], mini_index.groups
    change = {g: np.mean([rows["vqf_tuned"][n]["total"] for n in m]) / np.mean([rows["vqf_defaults"][n]["total"]
                                                                               for n in m]) - 1.0
              for g, m in groups.items() if len(m) >= 2}
    worst = max(change, key=change.get)
    assert len(cells) == 17 and cells[16] == f"{worst} {100.0 * change[worst]:+.1f} %"
    doc = json.loads(json.dumps(per_sensor_json({name: plan})))
    n = plan["folds"][0][0]
    assert doc[name]["sizes"]["0"]["relearned"][n]["total"] == plan["sizes"][0]["relearned"][n]["total"]
    assert doc[name]["guard_kept"] == {"0": [False, False, False]}


def test_script_says_what_is_missing(tmp_path, capsys):
    sys.path.insert(0, str(PIPELINES))
    try:
        import per_sensor as script
    finally:
        sys.path.remove(str(PIPELINES))
    with pytest.raises(SystemExit) as exc:
        script.main(["--data", str(tmp_path / "nowhere")])
    assert exc.value.code == 2 and "no trials.json" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        script.main(["--sizes", "1,all"])
    assert "a whole number of recordings >= 2" in capsys.readouterr().err


def test_half_is_the_kept_back_split_in_its_own_files(learning_off, mini_index, tmp_path, monkeypatch, capsys):
    """``--half``: 2 folds, all of each half re-learned on and trained on (``HALF``), written to
    per_sensor_half.md / .json with the models in <work>_half; refused together with --quick. The
    protocol itself is replaced by the fixture's result (its run is the slow part, tested above)."""
    sys.path.insert(0, str(PIPELINES))
    try:
        import per_sensor as script
    finally:
        sys.path.remove(str(PIPELINES))
    assert (HALF.folds, HALF.sizes, HALF.scratch_sizes) == (2, (0,), (0,))
    seen = {}

    def fake(dirs, work, bases, settings, config=None):
        seen.update(work=work, settings=settings, config=config)
        return {Path(mini_index.root).name: learning_off[0]}
    monkeypatch.setattr(script, "per_sensor", fake)
    monkeypatch.setattr(script, "base_models", lambda dirs, base_from, work: {})
    assert script.main(["--half", "--data", str(mini_index.root), "--out", str(tmp_path / "out"),
                        "--work", str(tmp_path / "w")]) == 0
    assert seen == {"work": tmp_path / "w_half", "settings": HALF, "config": None}
    assert (tmp_path / "out" / "per_sensor_half.md").read_text().startswith(
        "*Generated by `python pipelines/per_sensor.py --half ")
    assert (tmp_path / "out" / "per_sensor_half.json").is_file() and not (tmp_path / "out" / "per_sensor.md").exists()
    capsys.readouterr()
    with pytest.raises(SystemExit):
        script.main(["--half", "--quick"])
    assert "--quick and --half: one of them" in capsys.readouterr().err
    # --config: the re-learning's and the scratch training's config, passed on; a missing file is one line
    cfg = tmp_path / "mine.toml"
    cfg.write_text("")
    assert script.main(["--half", "--data", str(mini_index.root), "--out", str(tmp_path / "out2"),
                        "--work", str(tmp_path / "w"), "--config", str(cfg)]) == 0
    assert seen["config"] == str(cfg)
    capsys.readouterr()
    with pytest.raises(SystemExit):
        script.main(["--half", "--config", str(tmp_path / "nope.toml")])
    assert f"--config {tmp_path / 'nope.toml'}: no such file" in capsys.readouterr().err
    # --field-change: the config's [gains.vqf] (the scratch training) and [gains.relearn] search σ_f
    # (FIELD_CHANGE_GRID); its own files and models
    assert script.main(["--half", "--field-change", "--data", str(mini_index.root), "--out", str(tmp_path / "out3"),
                        "--work", str(tmp_path / "w")]) == 0
    assert seen["work"] == tmp_path / "w_half_field_change"
    assert seen["config"]["gains"]["vqf"]["field_change_scale"] == list(FIELD_CHANGE_GRID)
    assert VQFGainSearch.from_dict(seen["config"]["gains"]["vqf"]).field_change_scale == FIELD_CHANGE_GRID
    assert seen["config"]["gains"]["relearn"]["field_change_scale"] == list(FIELD_CHANGE_GRID)
    assert sorted(q.name for q in (tmp_path / "out3").iterdir()) == ["per_sensor_half_field_change.json",
                                                                     "per_sensor_half_field_change.md"]
