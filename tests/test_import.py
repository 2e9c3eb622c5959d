"""``togglecf import``: a simulated recording with a known clock offset and mounting rotation,
written the way a user's logger would (dps, g, milliseconds with jitter, a NED mocap reference as
xyzw quaternions on its own clock), comes back with both recovered; a real phone trial written out
as CSV and imported back scores the same; bad input is one line naming file and column."""
import json
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

import togglecf.simulate as sim
from togglecf.cli.main import main
from togglecf.core import quaternion as quat
from togglecf.core.units import ACC_UNITS, GYR_UNITS, MAG_UNITS
from togglecf.data.broad import DatasetIndex, load_trial
from togglecf.data.importer import ImportSettings, broad_movement, import_recording
from togglecf.registry import FilterSpec
from togglecf.run.scoring import score_trial

ROOT = Path(__file__).resolve().parents[1]
PHONE = ROOT.parent / "shared" / "data" / "tyrex_nexus5"
PHONE_TRIAL = "Jakob_Nexus5_NoDist_AR"

FS = 100.0  # Hz, the IMU's nominal rate
OFFSET_S = 0.037  # the IMU's stamp minus the reference's stamp of the same instant
MOUNT_DEG = 20.0
MOUNT_AXIS = np.array([1.0, 2.0, -1.0]) / np.sqrt(6.0)
#: the reference's earth frame: tilted by ~1° and turned by 30° against ENU, then written as NED
FRAME_RPY_DEG = (0.8, -0.5, 30.0)

IMU_HEADER = "t,gyr_x,gyr_y,gyr_z,acc_x,acc_y,acc_z,mag_x,mag_y,mag_z"


def _write_csv(path, header: str, columns) -> Path:
    np.savetxt(path, np.column_stack(columns), delimiter=",", header=header, comments="", fmt="%.17g")
    return path


def _smooth_motion(duration_s: float, seed: int = 3):
    """A function of time [s] -> orientation ``(n, 4)`` (sensor -> ENU): smooth random rotation on a
    1 kHz grid, read between its samples by SLERP, so that the IMU and the mocap can sample it at
    their own instants."""
    fine = 1000.0
    q = sim.rest_then_motion_trajectory(fine, 1.0, duration_s, max_rate=2.0, seed=seed)

    def at(t):
        ind = np.clip(np.asarray(t) * fine, 0.0, q.shape[0] - 1.000001)
        i = np.floor(ind).astype(int)
        return quat.slerp(q[i], q[i + 1], ind - i)
    return at


@pytest.fixture(scope="module")
def simulated_logs(tmp_path_factory):
    """IMU at 100 Hz with ±1 ms sampling jitter (stamps in ms), and a 120-Hz mocap log of a marker
    mounted 20° from the IMU, on a clock 37 ms behind, in a tilted and turned NED frame, as xyzw."""
    d = tmp_path_factory.mktemp("sim_logs")
    rng = np.random.default_rng(1)
    motion = _smooth_motion(21.0)
    n = int(20.0 * FS)
    t_imu = 0.05 + np.arange(n) / FS + rng.uniform(-1e-3, 1e-3, n)
    q_imu = motion(t_imu)
    imu = sim.imu_from_orientation(q_imu, FS, gyro_noise=0.004, acc_noise=0.03, mag_noise=0.3, seed=2)
    gyr = imu.gyr.copy()
    gyr[1:] *= (1.0 / FS) / np.diff(t_imu)[:, None]  # the rate over the real step, not the nominal one
    mount = quat.from_rotvec(np.radians(MOUNT_DEG) * MOUNT_AXIS)
    t_ref = np.arange(0.0, 21.0, 1.0 / 120.0)
    q_marker = quat.multiply(motion(t_ref + OFFSET_S), quat.conjugate(mount))
    frame = quat.from_euler_zyx(np.radians(FRAME_RPY_DEG))
    q_ref_ned = quat.to_frame(quat.multiply(quat.conjugate(frame), q_marker), "NED")
    imu_csv = _write_csv(d / "imu.csv", IMU_HEADER, [1e3 * t_imu, gyr / GYR_UNITS["dps"], imu.acc / ACC_UNITS["g"],
                                                     imu.mag])
    ref_csv = _write_csv(d / "mocap.csv", "t,q0,q1,q2,q3", [1e3 * t_ref, q_ref_ned[:, [1, 2, 3, 0]]])
    return {"imu": imu_csv, "ref": ref_csv, "q_imu": q_imu, "t_imu": t_imu, "mount": mount}


def test_a_known_clock_offset_and_mounting_rotation_are_recovered(simulated_logs, tmp_path, capsys):
    out = tmp_path / "data"
    rc = main(["import", str(simulated_logs["imu"]), "--reference", str(simulated_logs["ref"]), "--out", str(out),
               "--name", "sim", "--units", "gyr=dps,acc=g,mag=uT", "--frame", "ned", "--quat-order", "xyzw",
               "--time-unit", "ms"])
    text = capsys.readouterr().out
    assert rc == 0, text
    assert "clock offset" in text and "IMU-to-marker rotation" in text
    ref = json.loads((out / "sim.import.json").read_text())["reference"]
    offset_err_ms = 1e3 * abs(ref["clock_offset_s"] - OFFSET_S)
    rotation_err_deg = np.degrees(quat.angle_between(np.array(ref["imu_to_marker"]), simulated_logs["mount"]))
    print(f"recovered: offset error {offset_err_ms:.3f} ms, mounting rotation error {rotation_err_deg:.4f}°")
    # 2 ms: a fifth of a sample at 100 Hz; qmt refines the offset below its 1-ms correlation grid, and the
    # ±1 ms jitter of the stamps averages out over 2000 samples
    assert offset_err_ms < 2.0
    # 0.5°: with noise-free axes the fit of gyro to mocap rates (2000 samples of 2 rad/s motion against
    # 0.004 rad/s gyro noise) leaves hundredths of a degree; a tenth of BROAD's smallest errors (~5°)
    assert rotation_err_deg < 0.5
    assert abs(ref["reference_heading_deg"] - FRAME_RPY_DEG[2]) < 1.0  # the mocap frame's heading, from the mag
    trial = DatasetIndex.from_dir(out).load("sim")
    assert trial.time is not None and np.allclose(trial.time, simulated_logs["t_imu"], atol=1e-12)
    assert trial.fs == pytest.approx(FS, rel=5e-3)  # the median rate of stamps with ±10 % jitter: within 0.5 %
    truth_err = np.degrees(quat.angle_between(trial.opt_quat, simulated_logs["q_imu"]))
    assert np.nanmax(truth_err[1:-1]) < 0.5  # the aligned reference is the IMU's true orientation
    assert (out / "sim.import.png").is_file()


def _phone_trial():
    if not (PHONE / f"{PHONE_TRIAL}.hdf5").is_file():
        pytest.skip(f"the phone data is not beside the repository ({PHONE})")
    return load_trial(PHONE / f"{PHONE_TRIAL}.hdf5").slice(0, 3000)  # 30 s: fast, and movement throughout


@pytest.mark.broad
def test_a_phone_trial_written_as_csv_and_imported_back_scores_the_same(tmp_path):
    """The phone trial written the way another logger might (ms, dps, g, gauss, xyzw in NED) and
    read back: Madgwick and the VQF core give the original's errors."""
    orig = _phone_trial()
    t = np.arange(orig.n_samples) / orig.fs
    q_ned = quat.to_frame(orig.opt_quat, "NED")[:, [1, 2, 3, 0]]
    csv = _write_csv(tmp_path / "phone.csv", IMU_HEADER + ",q0,q1,q2,q3,movement",
                     [1e3 * t, orig.gyr / GYR_UNITS["dps"], orig.acc / ACC_UNITS["g"], orig.mag / MAG_UNITS["gauss"],
                      q_ned, orig.movement.astype(int)])
    res = import_recording(csv, tmp_path / "data", settings=ImportSettings(
        units="gyr=dps,acc=g,mag=gauss", time_unit="ms", frame="ned", quat_order="xyzw"))
    back = DatasetIndex.from_dir(tmp_path / "data").load("phone")
    assert back.fs == pytest.approx(orig.fs, rel=1e-9) and np.array_equal(back.movement, orig.movement)
    assert res.report["reference_from"].startswith("the log's own quaternion columns")
    for name in ("madgwick", "vqf_core"):
        spec = FilterSpec(name)
        want, _ = score_trial(orig, spec)
        got, _ = score_trial(back, spec)
        for key in ("total", "heading", "inclination"):
            diff = abs(got.errors[key] - want.errors[key])
            print(f"{name} {key}: original {want.errors[key]:.4f}°, imported {got.errors[key]:.4f}°, "
                  f"diff {diff:.2e}°")
            assert diff < 0.05


@pytest.mark.broad
def test_the_movement_rule_matches_the_phone_datas_own_mask():
    """BROAD's rule from the gyroscope gives the mask the phone data was made with (the optical rate)."""
    orig = load_trial(_phone_trial().source)
    assert np.mean(broad_movement(orig.gyr, orig.fs) == orig.movement) > 0.97


# ----------------------------------------------------------------------------------- bad input

def _small_log(tmp_path, header=IMU_HEADER, t=None, edit=None, extra=()) -> Path:
    """A 3-s log in the package's units; ``edit(columns)`` spoils it, ``extra`` adds columns."""
    n = 300
    q = sim.random_smooth_trajectory(FS, n / FS, seed=4)
    imu = sim.imu_from_orientation(q, FS)
    cols = np.column_stack([np.arange(n) / FS if t is None else t, imu.gyr, imu.acc, imu.mag, *extra])
    if edit is not None:
        edit(cols)
    return _write_csv(tmp_path / "log.csv", header, [cols])


def _run_import(capsys, *argv):
    rc = main(["import", *map(str, argv)])
    err = capsys.readouterr().err.strip()
    return rc, err


@pytest.mark.parametrize("case,needle", [
    ("missing_column", "field 'mag_z': missing column"),
    ("time_not_increasing", "field 't': time stamps must increase: row 5"),
    ("nan_only_column", "field 'acc_y': no finite value"),
    ("unknown_unit", "--units: unknown unit 'furlong/s' for gyr"),
    ("quaternion_order", "field 'q0': row 0: quaternion norm"),
    ("units_forgotten", "field 'acc': median |acc| = 1: looks like g"),
])
def test_bad_input_is_one_line_naming_the_file_and_column(case, needle, tmp_path, capsys):
    argv = []
    if case == "missing_column":
        log = _small_log(tmp_path, header=IMU_HEADER.replace(",mag_z", ",temperature"))
    elif case == "time_not_increasing":
        t = np.arange(300) / FS
        t[5] = t[4]
        log = _small_log(tmp_path, t=t)
    elif case == "nan_only_column":
        log = _small_log(tmp_path, edit=lambda c: c.__setitem__((slice(None), 5), np.nan))
    elif case == "unknown_unit":
        log, argv = _small_log(tmp_path), ["--units", "gyr=furlong/s"]
    elif case == "units_forgotten":  # a log in g read as m/s²: the trial's unit check, naming --units
        log = _small_log(tmp_path, edit=lambda c: c.__setitem__((slice(None), slice(4, 7)), c[:, 4:7] / 9.81))
    else:  # a quaternion that is not one (wrong scale): refused, not imported as garbage
        log = _small_log(tmp_path, header=IMU_HEADER + ",q0,q1,q2,q3", extra=[np.tile([2.0, 0.0, 0.0, 0.0], (300, 1))])
    rc, err = _run_import(capsys, log, "--out", tmp_path / "out", *argv)
    assert rc == 1
    assert len(err.splitlines()) == 1 and "Traceback" not in err, err
    assert needle in err, err
    if case != "unknown_unit":
        assert str(log) in err
    assert not (tmp_path / "out" / "trials.json").exists()


def test_a_reference_without_qmt_says_which_extra_and_no_reference_needs_none(tmp_path, capsys, monkeypatch):
    monkeypatch.setitem(sys.modules, "qmt", None)  # as if qmt were not installed
    log = _small_log(tmp_path)
    rc, err = _run_import(capsys, log, "--reference", log, "--out", tmp_path / "out")
    assert rc == 1
    assert err == "togglecf import --reference needs the [import] extra: pip install 'togglecf[import]'"
    rc, err = _run_import(capsys, log, "--out", tmp_path / "out", "--name", "plain")
    assert rc == 0, err
    trial = DatasetIndex.from_dir(tmp_path / "out").load("plain")
    assert np.isnan(trial.opt_quat).all() and trial.time is not None and trial.groups == ("imported",)


def test_npz_and_npy_logs_read_like_the_csv(tmp_path):
    n = 300
    q = sim.random_smooth_trajectory(FS, n / FS, seed=5)
    imu = sim.imu_from_orientation(q, FS)
    t = np.arange(n) / FS
    np.savez(tmp_path / "a.npz", t=t, gyr=imu.gyr, acc=imu.acc, mag=imu.mag, quat=q)
    np.save(tmp_path / "b.npy", np.column_stack([t, imu.gyr, imu.acc, imu.mag, q]))
    a = import_recording(tmp_path / "a.npz", tmp_path / "out").trial
    b = import_recording(tmp_path / "b.npy", tmp_path / "out").trial
    for x in (a, b):
        assert np.allclose(x.opt_quat, q) and np.allclose(x.gyr, imu.gyr) and np.allclose(x.time, t)
    assert sorted(DatasetIndex.from_dir(tmp_path / "out").available) == ["a", "b"]


def test_the_command_has_its_help(capsys):
    with pytest.raises(SystemExit) as exc:
        main(["import", "--help"])
    assert exc.value.code == 0
    out = capsys.readouterr().out
    assert out.startswith("usage: togglecf import") and "--reference" in out and "--quat-order" in out


def test_scoring_integrates_with_the_time_stamps_of_an_irregular_log():
    """An imported log keeps its time stamps (``Trial.time``); evaluation runs the filters with their
    per-sample Δt. A 400 Hz simulation kept at every 4th sample with every 5th kept sample dropped
    (steps of 10 and 20 ms, median 10 ms): pure gyro integration with the stamps follows the truth
    to the simulator's discretisation (< 0.5°), at the nominal 100 Hz it loses a fifth of every turn."""
    q = sim.random_smooth_trajectory(400.0, 30.0, max_rate=1.0, seed=3)
    dense = sim.imu_from_orientation(q, 400.0, seed=3)
    keep = np.arange(0, len(q), 4)
    keep = keep[np.arange(keep.size) % 5 != 4]
    sub = replace(dense, fs=100.0, gyr=dense.gyr[keep], acc=dense.acc[keep], mag=dense.mag[keep],
                  opt_quat=dense.opt_quat[keep], opt_pos=None, movement=np.ones(keep.size, bool))
    with_stamps = replace(sub, time=keep / 400.0)
    spec = FilterSpec("gyro")
    stamped = score_trial(with_stamps, spec)[0].errors["total"]
    nominal = score_trial(sub, spec)[0].errors["total"]
    assert stamped < 0.5 < 10 * stamped < nominal, (stamped, nominal)
