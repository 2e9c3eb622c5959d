"""Several data directories at once (``--data A --data B``, ``[run] data``), trial names that carry
their dataset, selection by dataset, and trials without ``opt_pos`` (evaluation needs none; training
refuses with one line naming file, field and why)."""
import json
import shutil
from dataclasses import replace
from pathlib import Path

import pytest

from conftest import TINY_TRAIN_TOML
from togglecf.cli.main import main
from togglecf.data.broad import (DataError, DatasetIndex, MultiIndex, copy_hdf5_trial, load_trial, open_index,
                                 trial_fields)
from togglecf.learn.labels import make_targets
from togglecf.parallel.backend import data_location, load_trial_cached

#: set by ``_mini_data``: the mini directory, its trial names (02, 07, 24) and its directory name, the
#: dataset part of the names in a combined index (``broad_mini``: the real cuts; ``synthetic_mini``)
MINI_DIR, MINI_NAMES, DS = None, [], ""


@pytest.fixture(autouse=True)
def _mini_data(mini_index, mini_names):
    """Every test here reads the mini directory (the real cuts from BROAD, or the synthetic trials
    without it; made on first use)."""
    global MINI_DIR, MINI_NAMES, DS
    MINI_DIR, MINI_NAMES, DS = Path(mini_index.root), list(mini_names), Path(mini_index.root).name


@pytest.fixture
def two_dirs(tmp_path):
    """The shipped mini directory and a copy of it called ``phone``."""
    copy = tmp_path / "phone"
    shutil.copytree(MINI_DIR, copy)
    return MINI_DIR, copy


def _without_opt_pos(src: Path, dest_dir: Path, name: str) -> Path:
    """``src`` (a BROAD HDF5 trial) rewritten as ``dest_dir/name.hdf5`` without ``opt_pos``, listed in
    ``dest_dir/trials.json`` (groups ``all_trials`` and ``undisturbed``)."""
    dest_dir.mkdir(parents=True, exist_ok=True)
    path = copy_hdf5_trial(src, dest_dir / f"{name}.hdf5", drop=("opt_pos",))
    index_file = dest_dir / "trials.json"
    info = json.loads(index_file.read_text()) if index_file.exists() else {
        "groups": [{"name": "all_trials"}, {"name": "undisturbed"}], "trials": {}}
    info["trials"][name] = {"description": "no opt_pos", "groups": ["all_trials", "undisturbed"]}
    index_file.write_text(json.dumps(info))
    return path


@pytest.fixture
def no_pos_dir(tmp_path):
    """A directory ``nopos`` with two mini trials written without ``opt_pos``."""
    d = tmp_path / "nopos"
    for n in MINI_NAMES[:2]:
        _without_opt_pos(MINI_DIR / f"{n}.hdf5", d, n)
    return d


# ------------------------------------------------------------------------------------ the index

def test_one_directory_keeps_plain_names(mini_index):
    idx = open_index([str(MINI_DIR)])
    assert isinstance(idx, DatasetIndex) and list(idx.available) == list(mini_index.available)
    assert isinstance(DatasetIndex.from_dirs([MINI_DIR]), DatasetIndex)
    # a selection written for several directories works on the one it names
    assert idx.select(f"{DS}/02,{DS}/") == [MINI_NAMES[0], *MINI_NAMES[1:]]


def test_combined_index_names_and_groups(two_dirs, mini_index):
    idx = open_index(list(two_dirs))
    assert isinstance(idx, MultiIndex) and idx.root == tuple(Path(d).resolve() for d in two_dirs)
    assert list(idx.available) == [f"{DS}/{n}" for n in MINI_NAMES] + [f"phone/{n}" for n in MINI_NAMES]
    # one group per dataset, then each directory's trials.json groups with the same prefix
    assert idx.groups["phone"] == [f"phone/{n}" for n in MINI_NAMES]
    for g, members in mini_index.groups.items():
        assert idx.groups[f"{DS}/{g}"] == [f"{DS}/{t}" for t in members]
        assert idx.groups[f"phone/{g}"] == [f"phone/{t}" for t in members]
    assert "undisturbed" not in idx.groups  # no unprefixed groups: they would mix datasets silently
    t = idx.load(f"phone/{MINI_NAMES[2]}")
    assert t.name == f"phone/{MINI_NAMES[2]}" and t.groups[0] == "phone"
    assert set(t.groups[1:]) == {f"phone/{g}" for g in mini_index.trial_groups(MINI_NAMES[2])}
    assert "2 datasets" in idx.summary() and "phone/" in idx.summary()
    assert DatasetIndex.from_dirs(list(two_dirs)).available == idx.available


def test_selection_by_dataset_glob_and_item(two_dirs):
    idx = open_index(list(two_dirs))
    assert idx.select("phone/") == [f"phone/{n}" for n in MINI_NAMES]
    assert idx.select("phone/*") == idx.select("phone/")
    assert idx.select("02") == [f"{DS}/{MINI_NAMES[0]}", f"phone/{MINI_NAMES[0]}"]  # every dataset
    assert idx.select("*/24*") == [f"{DS}/{MINI_NAMES[2]}", f"phone/{MINI_NAMES[2]}"]
    assert idx.select(f"phone/07,{DS}/{MINI_NAMES[2]}") == [f"phone/{MINI_NAMES[1]}", f"{DS}/{MINI_NAMES[2]}"]
    assert idx.select(None) == list(idx.available)
    for bad in ("phone/99", "nowhere/02", "*NoSuch*"):
        with pytest.raises(KeyError):
            idx.select(bad)


def test_same_directory_name_twice_is_refused(tmp_path):
    a, b = tmp_path / "a" / "data", tmp_path / "b" / "data"
    shutil.copytree(MINI_DIR, a)
    shutil.copytree(MINI_DIR, b)
    with pytest.raises(ValueError, match="both called 'data'"):
        open_index([a, b])
    assert isinstance(open_index([a, a]), DatasetIndex)  # the same directory twice is kept once


def test_workers_load_from_the_combined_location(two_dirs):
    idx = open_index(list(two_dirs))
    loc = data_location(idx)
    assert isinstance(loc, tuple) and len(loc) == 2
    t = load_trial_cached(loc, f"phone/{MINI_NAMES[1]}")
    assert t.name == f"phone/{MINI_NAMES[1]}" and t.source == idx.available[t.name]
    with pytest.raises(KeyError):
        load_trial_cached(loc, MINI_NAMES[1])  # several directories: names carry them


# ------------------------------------------------------------------------------------- the CLI

def test_evaluate_on_two_directories(two_dirs, tmp_path, capsys):
    out = tmp_path / "out"
    rc = main(["evaluate", "--filter", "cf", "--data", str(two_dirs[0]), "--data", str(two_dirs[1]),
               "--trials", "02,phone/24", "--jobs", "2", "--out", str(out)])
    assert rc == 0
    text = capsys.readouterr().out
    for name in (f"{DS}/{MINI_NAMES[0]}", f"phone/{MINI_NAMES[0]}", f"phone/{MINI_NAMES[2]}"):
        assert name in text
    assert f"{DS}/{MINI_NAMES[2]}" not in text
    assert f"  {DS}: mean over 1 trials" in text and "  phone: mean over 2 trials" in text
    res = json.loads((out / "results.json").read_text())
    assert res["data_dir"] == [str(Path(d).resolve()) for d in two_dirs]
    assert {DS, "phone", "phone/undisturbed", "phone/disturbed"} <= set(res["per_group"])
    assert res["per_group"]["phone"]["n_trials"] == 2


def test_evaluate_data_from_config(two_dirs, tmp_path, capsys):
    cfg = tmp_path / "run.toml"
    cfg.write_text(f'[run]\ndata = ["{two_dirs[0]}", "{two_dirs[1]}"]\n')
    assert main(["evaluate", "--filter", "cf", "--config", str(cfg), "--trials", "phone/02", "--jobs", "1"]) == 0
    assert f"phone/{MINI_NAMES[0]}" in capsys.readouterr().out
    # --data overrides the config's directories
    assert main(["evaluate", "--filter", "cf", "--config", str(cfg), "--data", str(two_dirs[1]), "--trials", "02",
                 "--jobs", "1"]) == 0
    out = capsys.readouterr().out
    assert MINI_NAMES[0] in out and "phone/" not in out
    cfg.write_text("[run]\ndata = 3\n")
    assert main(["evaluate", "--filter", "cf", "--config", str(cfg), "--jobs", "1"]) == 1
    assert "data must be a directory or a list" in capsys.readouterr().err


# ------------------------------------------------------------------------------ without opt_pos

def test_trial_without_opt_pos_loads_and_evaluates(no_pos_dir, tmp_path, capsys):
    path = no_pos_dir / f"{MINI_NAMES[0]}.hdf5"
    assert "opt_pos" not in trial_fields(path)
    t = load_trial(path)
    assert t.opt_pos is None and t.slice(0, 500).opt_pos is None
    rc = main(["evaluate", "--filter", "madgwick", "--data", str(MINI_DIR), "--data", str(no_pos_dir),
               "--trials", f"nopos/,{DS}/02", "--jobs", "1"])
    assert rc == 0
    text = capsys.readouterr().out
    assert f"nopos/{MINI_NAMES[0]}" in text and "  nopos: mean over 2 trials" in text


def test_missing_required_field_is_still_named(tmp_path):
    path = copy_hdf5_trial(MINI_DIR / f"{MINI_NAMES[0]}.hdf5", tmp_path / "x.hdf5", drop=("movement",))
    with pytest.raises(DataError, match=r"field 'movement': missing dataset"):
        load_trial(path)


def test_labels_without_opt_pos_come_from_the_reference_orientation(no_pos_dir, mini_index, mini_names):
    """No optical position: the linear acceleration is the IMU's specific force beyond R_trueᵀ g, smoothed
    as the optical derivative is. Against the optical labels of the same trials, measured (real cuts):
    98.6 % of the valid samples agree on slow rotation (02), 80.3 % on fast rotation (07: the IMU feels
    the centripetal acceleration at its own place, which the markers' position does not, so more
    vibration and less linear acceleration), 92.9 % on tapping (24). Bounds: 95 % and 75 %."""
    t = load_trial(no_pos_dir / f"{MINI_NAMES[0]}.hdf5")
    assert t.opt_pos is None
    imu = make_targets(t)
    assert imu.lin_acc_source == "imu" and imu.valid.mean() > 0.9
    agree = []
    for n in mini_names:
        full = mini_index.load(n)
        a, b = make_targets(full), make_targets(replace(full, opt_pos=None))
        assert a.lin_acc_source == "opt_pos" and b.lin_acc_source == "imu"
        v = a.valid & b.valid
        agree.append(float((a.state[v] == b.state[v]).mean()))
    assert agree[0] > 0.95 and min(agree) > 0.75, agree


def test_train_takes_trials_without_opt_pos_and_says_where_labels_came_from(no_pos_dir, tmp_path):
    cfg = tmp_path / "tiny.toml"
    cfg.write_text(TINY_TRAIN_TOML)
    rc = main(["train", "--config", str(cfg), "--data", str(MINI_DIR), "--data", str(no_pos_dir),
               "--trials", f"{DS}/02,{DS}/07,nopos/02", "--out", str(tmp_path / "m"), "--no-cv"])
    assert rc == 0
    per = json.loads((tmp_path / "m" / "metadata.json").read_text())["per_trial"]
    assert per[f"nopos/{MINI_NAMES[0]}"]["lin_acc_source"] == "imu"
    assert per[f"{DS}/{MINI_NAMES[0]}"]["lin_acc_source"] == "opt_pos"


def test_train_on_two_directories_from_config(two_dirs, tmp_path):
    from togglecf.run.config import load_config
    from togglecf.run.train import run_training

    cfg = load_config({"run": {"data": [str(d) for d in two_dirs], "trials": f"{DS}/02,phone/07,phone/24"},
                       "classifier": {"n_estimators": 4, "max_depth": 3}, "regressor": {"n_estimators": 2,
                                                                                       "max_depth": 3},
                       "gains": {"learn": False}})
    res = run_training(cfg, out=tmp_path / "m", cv=False, verbose=False)
    meta = res["metadata"]
    assert meta["training_trials"] == [f"{DS}/{MINI_NAMES[0]}", f"phone/{MINI_NAMES[1]}",
                                       f"phone/{MINI_NAMES[2]}"]
    assert meta["data_dir"] == [str(Path(d).resolve()) for d in two_dirs]
    assert set(meta["data_files"]) == set(meta["training_trials"])
    # the pruning sweep finds the directories the models were trained on (names carry them)
    from togglecf.run.prune import _sweep_setup

    _, index, names, _ = _sweep_setup(tmp_path / "m", None, 2, 2)
    assert isinstance(index, MultiIndex) and names == meta["training_trials"]


def test_tune_on_two_directories(two_dirs, capsys):
    rc = main(["tune", "--filter", "madgwick", "--grid", "beta=0.05,0.1", "--data", str(two_dirs[0]), "--data",
               str(two_dirs[1]), "--trials", f"{DS}/02,phone/02", "--jobs", "1"])
    assert rc == 0
    out = capsys.readouterr().out
    assert "over 2 trials" in out and "phone/undisturbed" in out and f"{DS}/undisturbed" in out


# ------------------------------------------------------------------------------------ real data


@pytest.mark.broad
def test_broad_and_phone_data_together(broad_index, capsys):
    phone = broad_index.root.parent / "tyrex_nexus5"
    if not (phone / "trials.json").is_file():
        pytest.skip(f"no phone dataset at {phone}")
    idx = open_index([broad_index.root, phone])
    assert idx.select("tyrex_nexus5/") == [n for n in idx.available if n.startswith("tyrex_nexus5/")]
    assert len(idx.select("broad/")) == len(broad_index.available)
    assert "tyrex_nexus5/undisturbed" in idx.groups and "broad/undisturbed" in idx.groups
    t = idx.load(idx.select("tyrex_nexus5/*NoDist_AR")[0])
    assert t.fs == pytest.approx(100.0) and t.groups[0] == "tyrex_nexus5"
    rc = main(["evaluate", "--filter", "cf", "--data", str(broad_index.root), "--data", str(phone),
               "--trials", "broad/05,tyrex_nexus5/Guillaume_Nexus5_NoDist_AR", "--jobs", "2"])
    assert rc == 0
    text = capsys.readouterr().out
    assert "  broad: mean over 1 trials" in text and "  tyrex_nexus5: mean over 1 trials" in text
