"""BROAD data layer: both formats, the index, data-dir resolution and clear errors."""
import json
import os

import h5py
import numpy as np
import pytest
import scipy.io

from togglecf.data.broad import (
    MAX_INVALID_FRACTION,
    MIN_DURATION_S,
    DataError,
    DataNotFoundError,
    DatasetIndex,
    Trial,
    check_evaluable,
    load_trial,
    min_samples,
    resolve_data_dir,
    short_trial_name,
)
from togglecf.simulate import imu_from_orientation, random_smooth_trajectory

FS = 285.7142857142857


def synthetic_fields(n=600, seed=0):
    tr = imu_from_orientation(random_smooth_trajectory(FS, n / FS, seed=seed), FS, gyro_noise=0.01, seed=seed)
    q = tr.opt_quat.copy()
    q[10:20] = np.nan  # optical dropout, as in real BROAD
    pos = np.zeros((n, 3))
    pos[10:20] = np.nan
    mov = np.zeros(n, bool)
    mov[100:500] = True
    return dict(imu_gyr=tr.gyr, imu_acc=tr.acc, imu_mag=tr.mag, opt_quat=q, opt_pos=pos, movement=mov)


def write_hdf5(path, fields, fs=FS, drop=None):
    with h5py.File(path, "w") as f:
        for k, v in fields.items():
            if k != drop:
                f.create_dataset(k, data=v, compression="gzip")
        f.attrs["sampling_rate"] = fs


def write_mat(path, fields, fs=FS):
    d = dict(fields)
    d["movement"] = d["movement"].astype(np.uint8).reshape(-1, 1)  # BROAD stores (N, 1) uint8
    d["sampling_rate"] = np.array([[fs]])
    scipy.io.savemat(path, d)


def test_hdf5_and_mat_give_the_same_trial(tmp_path):
    fields = synthetic_fields()
    write_hdf5(tmp_path / "x.hdf5", fields)
    write_mat(tmp_path / "x.mat", fields)
    a, b = load_trial(tmp_path / "x.hdf5"), load_trial(tmp_path / "x.mat")
    assert a.fs == b.fs == pytest.approx(FS)
    for k in ("gyr", "acc", "mag", "opt_quat", "opt_pos", "movement"):
        np.testing.assert_array_equal(getattr(a, k), getattr(b, k))
    assert b.movement.dtype == bool and b.movement.shape == (600,)
    assert a.name == "x"


@pytest.mark.parametrize("fmt", ["hdf5", "mat"])
def test_missing_field_named(tmp_path, fmt):
    fields = synthetic_fields()
    if fmt == "hdf5":
        write_hdf5(tmp_path / "t.hdf5", fields, drop="imu_mag")
    else:
        del fields["imu_mag"]
        write_mat(tmp_path / "t.mat", fields)
    with pytest.raises(DataError, match=rf"t\.{fmt}: field 'imu_mag': missing"):
        load_trial(tmp_path / f"t.{fmt}")


def test_wrong_shape_named(tmp_path):
    fields = synthetic_fields()
    fields["imu_acc"] = fields["imu_acc"][:, :2]
    write_hdf5(tmp_path / "t.hdf5", fields)
    with pytest.raises(DataError, match=r"t\.hdf5: field 'acc': expected shape \(N, 3\), got \(600, 2\)"):
        load_trial(tmp_path / "t.hdf5")


def test_length_mismatch_named(tmp_path):
    fields = synthetic_fields()
    fields["imu_mag"] = fields["imu_mag"][:-5]
    write_hdf5(tmp_path / "t.hdf5", fields)
    with pytest.raises(DataError, match="field 'mag': has 595 samples, gyr has 600"):
        load_trial(tmp_path / "t.hdf5")


def test_non_finite_imu_samples_accepted_and_counted(tmp_path):
    """A NaN burst is kept (the filters skip bad samples) and counted per field."""
    fields = synthetic_fields()
    fields["imu_gyr"][42, 1] = np.inf
    fields["imu_acc"][100:130] = np.nan
    fields["imu_mag"][100:105, 0] = np.nan  # same samples as acc: counted once in n_invalid
    write_hdf5(tmp_path / "t.hdf5", fields)
    t = load_trial(tmp_path / "t.hdf5")
    assert t.invalid == {"gyr": 1, "acc": 30, "mag": 5} and t.n_invalid == 31
    assert t.slice(0, 110).invalid == {"gyr": 1, "acc": 10, "mag": 5}
    assert load_trial(tmp_path / "t.hdf5").slice(200, 600).n_invalid == 0


def test_too_many_non_finite_samples_refused(tmp_path):
    """More than MAX_INVALID_FRACTION of one field non-finite: refused, naming file, field, fraction."""
    fields = synthetic_fields()  # 600 samples: 10 % = 60
    fields["imu_mag"][200:260] = np.nan
    write_hdf5(tmp_path / "ok.hdf5", fields)
    assert load_trial(tmp_path / "ok.hdf5").invalid["mag"] == 60  # exactly 10 %: accepted
    fields["imu_mag"][260] = np.nan
    write_hdf5(tmp_path / "t.hdf5", fields)
    with pytest.raises(DataError) as exc:
        load_trial(tmp_path / "t.hdf5")
    msg = str(exc.value)
    assert msg == (f"{tmp_path / 't.hdf5'}: field 'mag': 61 of 600 samples (10.2%) are not finite (NaN/inf; first "
                   "at index 200); at most 10% may be (togglecf.data.broad.MAX_INVALID_FRACTION)")
    assert MAX_INVALID_FRACTION == 0.10


def test_too_short_trial_refused(tmp_path):
    """A recording shorter than MIN_DURATION_S is refused at load time, naming file and minimum."""
    fields = {k: v[:10] for k, v in synthetic_fields().items()}
    write_hdf5(tmp_path / "short.hdf5", fields)
    with pytest.raises(DataError) as exc:
        load_trial(tmp_path / "short.hdf5")
    assert str(exc.value) == (f"{tmp_path / 'short.hdf5'}: field 'imu_gyr': 10 samples (0.03 s at 285.7 Hz) is too "
                              "short: at least 285 samples (1 s, togglecf.data.broad.MIN_DURATION_S) are needed to "
                              "evaluate a filter")
    assert min_samples(FS) == 285 and MIN_DURATION_S == 1.0
    # in memory (a slice): refused when it is to be evaluated
    t = load_trial_ok(tmp_path)
    with pytest.raises(DataError, match=r"10 samples \(0\.03 s at 285\.7 Hz\) is too short: at least 285"):
        check_evaluable(t.slice(0, 10))
    # long enough but nothing to score: no movement sample with ground truth
    with pytest.raises(DataError, match="no sample is both marked as movement and has ground truth"):
        check_evaluable(t.slice(0, 300).__class__(**{**_trial_kwargs(t.slice(0, 300)),
                                                      "movement": np.zeros(300, bool)}))
    assert check_evaluable(t) is t


def load_trial_ok(tmp_path):
    write_hdf5(tmp_path / "ok.hdf5", synthetic_fields())
    return load_trial(tmp_path / "ok.hdf5")


def _trial_kwargs(t):
    return dict(name=t.name, fs=t.fs, gyr=t.gyr, acc=t.acc, mag=t.mag, opt_quat=t.opt_quat, opt_pos=t.opt_pos,
                movement=t.movement, source=t.source, check_units=False)


def test_acc_in_g_detected(tmp_path):
    fields = synthetic_fields()
    fields["imu_acc"] = fields["imu_acc"] / 9.81
    write_hdf5(tmp_path / "t.hdf5", fields)
    with pytest.raises(DataError, match="field 'acc'.*looks like g, expected m/s²"):
        load_trial(tmp_path / "t.hdf5")


def test_acc_in_mg_detected(tmp_path):
    fields = synthetic_fields()
    fields["imu_acc"] = fields["imu_acc"] / 9.81 * 1000.0
    write_hdf5(tmp_path / "t.hdf5", fields)
    with pytest.raises(DataError, match="field 'acc'.*looks like mg, expected m/s²"):
        load_trial(tmp_path / "t.hdf5")


def test_vigorous_motion_is_not_a_unit_error(tmp_path):
    # a phone in a running hand reads a median |acc| of 20-24 m/s² (the iPhone 4S RunningHand trials);
    # no other unit explains that, so it must load (issue 25: it was refused as "implausible")
    fields = synthetic_fields()
    fields["imu_acc"] = fields["imu_acc"] * 2.4
    write_hdf5(tmp_path / "t.hdf5", fields)
    t = load_trial(tmp_path / "t.hdf5")
    assert 20.0 < np.median(np.linalg.norm(t.acc, axis=1)) < 26.0


def test_gyro_in_deg_per_s_detected(tmp_path):
    fields = synthetic_fields()
    fields["imu_gyr"] = np.degrees(fields["imu_gyr"]) * 10  # a fast trial in °/s
    write_hdf5(tmp_path / "t.hdf5", fields)
    with pytest.raises(DataError, match="field 'gyr'.*looks like °/s, expected rad/s"):
        load_trial(tmp_path / "t.hdf5")


def test_corrupt_hdf5_and_truncated_mat(tmp_path):
    fields = synthetic_fields()
    write_hdf5(tmp_path / "good.hdf5", fields)
    (tmp_path / "bad.hdf5").write_bytes((tmp_path / "good.hdf5").read_bytes()[:3000])
    with pytest.raises(DataError, match=r"bad\.hdf5: cannot read HDF5 file"):
        load_trial(tmp_path / "bad.hdf5")
    write_mat(tmp_path / "good.mat", fields)
    raw = (tmp_path / "good.mat").read_bytes()
    (tmp_path / "bad.mat").write_bytes(raw[: len(raw) // 2])
    with pytest.raises(DataError, match=r"bad\.mat: cannot read MAT file"):
        load_trial(tmp_path / "bad.mat")
    (tmp_path / "t.csv").write_text("1,2,3")
    with pytest.raises(DataError, match="unknown trial format"):
        load_trial(tmp_path / "t.csv")
    with pytest.raises(DataError, match="file not found"):
        load_trial(tmp_path / "nope.hdf5")


def test_trial_validates_in_memory_input():
    f = synthetic_fields(200)
    with pytest.raises(DataError, match="sampling_rate.*positive"):
        Trial("x", 0.0, f["imu_gyr"], f["imu_acc"], f["imu_mag"], f["opt_quat"], f["opt_pos"], f["movement"])
    q = f["opt_quat"].copy()
    q[50, 2] = np.nan
    with pytest.raises(DataError, match="opt_quat.*all finite or all NaN"):
        Trial("x", FS, f["imu_gyr"], f["imu_acc"], f["imu_mag"], q, f["opt_pos"], f["movement"])


def make_broad_dir(root, names, listed, fmt="hdf5"):
    root.mkdir(parents=True, exist_ok=True)
    info = {"groups": [{"name": "all_trials", "level": 0, "category": ""}, {"name": "g1", "level": 1, "category": ""}],
            "trials": {n: {"description": "", "groups": ["all_trials"] + (["g1"] if i % 2 == 0 else [])}
                       for i, n in enumerate(listed)}}
    (root / "trials.json").write_text(json.dumps(info))
    for i, n in enumerate(names):
        (write_hdf5 if fmt == "hdf5" else write_mat)(root / f"{n}.{fmt}", synthetic_fields(300, seed=i))
    return root


def test_index_reports_missing_and_unlisted(tmp_path):
    root = make_broad_dir(tmp_path / "b", ["01_a", "02_b", "99_extra"], ["01_a", "02_b", "03_c"])
    write_mat(root / "01_a.mat", synthetic_fields(300))  # both formats present: HDF5 preferred
    idx = DatasetIndex.from_dir(root)
    assert list(idx.available) == ["01_a", "02_b"]
    assert idx.available["01_a"].suffix == ".hdf5"
    assert idx.missing == ["03_c"]
    assert [p.name for p in idx.unlisted] == ["99_extra.hdf5"]
    assert idx.groups["g1"] == ["01_a", "03_c"]
    assert idx.select("2") == ["02_b"] and idx.select("01,02_b") == ["01_a", "02_b"]
    with pytest.raises(KeyError, match="not present"):
        idx.select("03")
    with pytest.raises(KeyError, match="not listed"):
        idx.select("42")
    t = idx.load("01_a")
    assert t.groups == ("all_trials", "g1")
    assert "missing (1): 03_c" in idx.summary() and "99_extra.hdf5" in idx.summary()


def test_resolve_data_dir_precedence(tmp_path, monkeypatch):
    a = make_broad_dir(tmp_path / "a", [], ["01_a"])
    b = make_broad_dir(tmp_path / "b", [], ["01_a"])
    monkeypatch.setenv("TOGGLECF_DATA", str(b))
    assert resolve_data_dir(a) == a.resolve()  # --data wins
    assert resolve_data_dir(None) == b.resolve()  # then the environment variable
    monkeypatch.setenv("TOGGLECF_DATA", str(tmp_path / "empty"))
    with pytest.raises(DataNotFoundError, match=r"given by \$TOGGLECF_DATA.*togglecf download"):
        resolve_data_dir(None)


def test_no_data_anywhere_gives_one_clear_message(tmp_path, monkeypatch):
    import togglecf.data.broad as data
    monkeypatch.delenv("TOGGLECF_DATA", raising=False)
    monkeypatch.setattr(data, "repo_root", lambda: None)
    monkeypatch.chdir(tmp_path)
    with pytest.raises(DataNotFoundError) as exc:
        resolve_data_dir(None)
    msg = str(exc.value)
    assert "BROAD data not found" in msg and "--data DIR" in msg and "togglecf download" in msg
    assert "github.com/dlaidig/broad" in msg


@pytest.mark.broad
def test_real_broad_index(broad_index):
    assert len(broad_index.trials) == 39 and len(broad_index.groups) == 16
    present = list(broad_index.available)
    assert len(present) >= 1
    if len(present) == 25:  # the shared/ subset: 17 HDF5 + 8 MAT
        suffixes = [p.suffix for p in broad_index.available.values()]
        assert suffixes.count(".hdf5") == 17 and suffixes.count(".mat") == 8
        assert len(broad_index.missing) == 14


@pytest.mark.broad
@pytest.mark.parametrize("name", ["01_undisturbed_slow_rotation_A", "02_undisturbed_slow_rotation_B"])
def test_real_trials_load_in_both_formats(broad_index, name):
    if name not in broad_index.available:
        pytest.skip(f"{name} not present")
    t = broad_index.load(name)
    assert t.fs == pytest.approx(285.714, abs=1e-3)
    assert t.gyr.shape == t.acc.shape == t.mag.shape == (t.n_samples, 3)
    assert t.movement.dtype == bool and 0.3 < t.movement.mean() < 0.9
    # acc at rest ~ g, mag norm tens of µT: units as documented
    assert 9.0 < np.median(np.linalg.norm(t.acc, axis=1)) < 10.6
    assert 20 < np.median(np.linalg.norm(t.mag, axis=1)) < 80


def test_atomic_writes_have_normal_permissions(tmp_path):
    import stat

    from togglecf.core.io import atomic_write_text
    p = atomic_write_text(tmp_path / "a" / "x.txt", "hello")
    mask = os.umask(0)
    os.umask(mask)
    assert stat.S_IMODE(p.stat().st_mode) == 0o666 & ~mask  # not mkstemp's 0600
    assert p.read_text() == "hello" and [q.name for q in p.parent.iterdir()] == ["x.txt"]  # no temp file left


def test_short_trial_names_keep_what_tells_trials_apart():
    # the RANSAC log and the CV table cut every name at its first underscore: all phone trials were "tyrex"
    assert short_trial_name("02_undisturbed_slow_rotation_B") == "02"
    assert short_trial_name("broad/02_undisturbed_slow_rotation_B") == "broad/02"
    assert short_trial_name("tyrex_nexus5/Thibaud_Nexus5_NoDist_Texting") == "tyrex_nexus5/Thibaud_Nexus5_NoDist_Texting"
    assert short_trial_name("Jakob_iPhone4S_NoDist_RunningHand") == "Jakob_iPhone4S_NoDist_RunningHand"
