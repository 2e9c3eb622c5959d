"""Create ``tests/data/synthetic_mini/``: three short *synthetic* trials in BROAD's layout, the
stand-in for the real cuts (``make_broad_mini.py``) on a machine without BROAD (see README.md).

    python tests/data/make_synthetic_mini.py [OUT_DIR]      # default: tests/data/synthetic_mini

Simulator output (``togglecf.simulate``), not recordings. Each trial is 4000 samples at 285.714 Hz
(14.0 s): 4 s of rest at a tilted orientation (``movement`` False), then 10 s of movement
(``movement`` True), as in the real cuts. The names start with the numbers of the real cuts
(``02_``, ``07_``, ``24_``: ``trials="02,07,24"`` selects them) and say what they are:

* ``02_synthetic_slow_rotation``: slow rotation (≤ 1.2 rad/s per axis), one quick translation;
* ``07_synthetic_fast_rotation_translation``: fast rotation (≤ 5 rad/s per axis), back-and-forth
  translations (peak ~5 m/s²) and 2 s of 40 Hz vibration;
* ``24_synthetic_tapping``: medium rotation, a few translations, 8 finger taps and a magnetic
  disturbance (a constant 20 µT field added for 2.5 s).

Ground truth: ``opt_quat`` is the exact orientation (sensor -> ENU), ``opt_pos`` the exact position
of the translations, whose second derivative is the linear acceleration in the accelerometer
(``simulate.translation_moves``). Vibration and taps are in the accelerometer only: their
displacements are micrometres (3 m/s² at 40 Hz: 0.05 mm), below what an optical system resolves,
which is what the ``vibration`` label means (``togglecf.learn.labels``). Sensor errors, as measured
at rest on the real cuts: white noise 0.0017 rad/s (gyro), 0.05 m/s² (acc), 0.67 µT (mag); a gyro
bias of a few mrad/s plus a random walk; the earth field ``simulate.EARTH_MAG_ENU`` (49 µT, 67° dip,
as in Berlin). Every motion state of ``labels.make_targets`` (rest, rotation, linear acceleration,
vibration) occurs in every pair of trials (``check`` below asserts it).

Deterministic: the same ``SEED`` gives the same bytes (no HDF5 timestamps). ``trials.json`` has the
structure of BROAD's: its 16 group definitions and one entry (``description``, ``groups``) per
trial. ``generator.json`` records script, seed and ``VERSION``; ``ensure`` rewrites a directory of
another version.
"""
from __future__ import annotations

import json
import shutil
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np

from togglecf import simulate as sim

OUT = Path(__file__).resolve().parent / "synthetic_mini"
SEED = 14  # issue 14: the mini tests without BROAD
VERSION = 1  # bump when the trials change: ensure() then rewrites an existing directory
FS = 2000.0 / 7.0  # BROAD's rate, 285.714 Hz
REST_S, MOTION_S = 4.0, 10.0  # 4000 samples
GYRO_NOISE, ACC_NOISE, MAG_NOISE = 0.0017, 0.05, 0.67  # rad/s, m/s², µT (std at rest of the real cuts)

#: BROAD's group definitions (names, levels, categories), so that group selections work as on BROAD
GROUPS = [
    {"name": "all_trials", "level": 0, "category": ""}, {"name": "undisturbed", "level": 1, "category": ""},
    {"name": "rotation", "level": 2, "category": "motion"}, {"name": "translation", "level": 2, "category": "motion"},
    {"name": "combined", "level": 2, "category": "motion"}, {"name": "slow", "level": 2, "category": "speed"},
    {"name": "fast", "level": 2, "category": "speed"}, {"name": "no_breaks", "level": 2, "category": "breaks"},
    {"name": "with_breaks", "level": 2, "category": "breaks"}, {"name": "disturbed", "level": 1, "category": ""},
    {"name": "tapping", "level": 2, "category": "disturbance"}, {"name": "vibration", "level": 2, "category": "disturbance"},
    {"name": "stationary_magnet", "level": 2, "category": "disturbance"},
    {"name": "attached_magnet", "level": 2, "category": "disturbance"},
    {"name": "office_environment", "level": 2, "category": "disturbance"},
    {"name": "mixed", "level": 2, "category": "disturbance"},
]

#: name -> what to simulate. Times in s from the start of the trial (movement from REST_S = 4 s).
TRIALS = {
    "02_synthetic_slow_rotation": dict(
        description="SYNTHETIC (togglecf.simulate, not a recording): slow rotation, one quick translation, "
                    "no breaks",
        groups=["all_trials", "undisturbed", "rotation", "slow", "no_breaks"],
        start_rpy_deg=(5.0, -10.0, 40.0), max_rate=1.2, knots_per_s=1.5, bias=(0.0035, 0.0020, -0.0040),
        moves=[(6.0, 1.5, (0.05, 0.08, 0.0)), (9.0, 0.45, (0.0, 0.0, 0.15)), (11.0, 1.5, (-0.05, -0.08, -0.15))],
        vibration=None, taps=(), mag=()),
    "07_synthetic_fast_rotation_translation": dict(
        description="SYNTHETIC (togglecf.simulate, not a recording): fast rotation with back-and-forth "
                    "translation, 2 s of 40 Hz vibration, no breaks",
        groups=["all_trials", "undisturbed", "combined", "fast", "no_breaks"],
        start_rpy_deg=(-8.0, 3.0, 120.0), max_rate=5.0, knots_per_s=3.0, bias=(0.0035, 0.0021, -0.0040),
        moves=[(5.0 + 0.6 * i, 0.5, (0.25 * (-1) ** i, 0.1 * (-1) ** i, 0.05 * (-1) ** i)) for i in range(10)],
        vibration=(3.0, 40.0, 11.5, 13.5), taps=(), mag=()),
    "24_synthetic_tapping": dict(
        description="SYNTHETIC (togglecf.simulate, not a recording): medium-speed rotation, some translation, "
                    "tapping, a magnetic disturbance, no breaks",
        groups=["all_trials", "disturbed", "tapping"],
        start_rpy_deg=(12.0, 6.0, -60.0), max_rate=2.5, knots_per_s=2.0, bias=(0.0084, -0.0035, -0.0045),
        moves=[(5.5, 0.5, (0.2, 0.0, 0.05)), (7.0, 0.5, (-0.2, 0.0, -0.05)), (10.5, 0.6, (0.0, 0.25, 0.0)),
               (12.0, 0.6, (0.0, -0.25, 0.0))],
        vibration=None, taps=(5.0, 6.3, 7.8, 8.6, 9.4, 11.2, 12.6, 13.3),
        mag=[(8.5, 11.0, (12.0, -10.0, 12.0))]),
}


def make_trial(name: str, spec: dict, seed: int):
    """The ``Trial`` of one entry of ``TRIALS`` (all randomness from ``seed``)."""
    n = int(round((REST_S + MOTION_S) * FS))
    q = sim.rest_then_motion_trajectory(FS, REST_S, MOTION_S, max_rate=spec["max_rate"],
                                        knots_per_s=spec["knots_per_s"], start_rpy_deg=spec["start_rpy_deg"],
                                        seed=seed)
    pos, lin_acc = sim.translation_moves(n, FS, spec["moves"], start_pos=(0.2, -0.1, 1.0))
    imu_acc = lin_acc.copy()  # what the IMU feels: the translations, plus vibration and taps
    if spec["vibration"]:
        amp, freq, start, stop = spec["vibration"]
        imu_acc += sim.vibration(n, FS, amplitude=amp, freq_hz=freq, start=start, stop=stop, seed=seed + 1)
    if spec["taps"]:
        imu_acc += sim.taps(n, FS, times=spec["taps"], peak=10.0, freq_hz=60.0, decay_s=0.02, seed=seed + 2)
    mag = sim.mag_disturbance_intervals(n, FS, spec["mag"]) if spec["mag"] else None
    bias = sim.random_walk_bias(n, FS, sigma=1e-4, initial=spec["bias"], seed=seed + 3)
    t = sim.imu_from_orientation(q, FS, gyro_noise=GYRO_NOISE, acc_noise=ACC_NOISE, mag_noise=MAG_NOISE,
                                 gyro_bias=bias, lin_acc_earth=imu_acc, mag_disturbance_earth=mag, seed=seed + 4)
    movement = np.arange(n) >= int(round(REST_S * FS))
    return replace(t, name=name, opt_pos=pos, movement=movement, groups=tuple(spec["groups"]))


def info_text(name: str, spec: dict, seed: int) -> str:
    return (f"SYNTHETIC trial {name}: simulator output (togglecf.simulate), NOT a recording and not BROAD data.\n"
            f"{spec['description']}.\n\nWritten by tests/data/make_synthetic_mini.py (version {VERSION}, seed {SEED}, "
            f"trial seed {seed}) for the togglecf tests on machines without BROAD. Layout and units as BROAD's: "
            "imu_gyr [rad/s], imu_acc [m/s²], imu_mag [µT] (sensor frame), opt_quat (sensor -> ENU, exact), "
            "opt_pos [m] (exact position of the simulated translations), movement (bool).")


def trial_seed(name: str) -> int:
    return SEED * 1000 + int(name[:2])


def make(out: Path = OUT) -> None:
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    index = {"groups": GROUPS, "trials": {n: {"description": s["description"], "groups": s["groups"]}
                                          for n, s in TRIALS.items()}}
    (out / "trials.json").write_text(json.dumps(index, indent=2, ensure_ascii=False) + "\n")
    for name, spec in TRIALS.items():
        seed = trial_seed(name)
        sim.write_broad_hdf5(out / f"{name}.hdf5", make_trial(name, spec, seed), info_text(name, spec, seed))
    (out / "generator.json").write_text(json.dumps(
        {"script": "tests/data/make_synthetic_mini.py", "version": VERSION, "seed": SEED}, indent=2) + "\n")


def ensure(out: Path = OUT) -> Path:
    """``out`` holding the synthetic trials of this ``VERSION``, written when missing or stale (to a
    sibling first, then renamed: never half-written)."""
    out = Path(out)
    stamp = out / "generator.json"
    if (out / "trials.json").is_file() and stamp.is_file() and json.loads(stamp.read_text()).get("version") == VERSION:
        return out
    tmp = out.with_name(out.name + ".partial")
    shutil.rmtree(tmp, ignore_errors=True)
    make(tmp)
    shutil.rmtree(out, ignore_errors=True)
    tmp.rename(out)
    return out


def check(out: Path = OUT) -> dict:
    """Motion-state counts per trial (``labels.make_targets``); asserts that every state occurs in
    every pair of trials."""
    from togglecf.data.broad import DatasetIndex
    from togglecf.learn.labels import STATE_NAMES, make_targets

    idx = DatasetIndex.from_dir(out)
    counts = {}
    for name in idx.available:
        st = make_targets(idx.load(name)).state
        counts[name] = np.bincount(st[st >= 0], minlength=len(STATE_NAMES))
    names = list(counts)
    for i, a in enumerate(names):
        for b in names[i + 1:]:
            assert np.all(counts[a] + counts[b] > 0), (a, b, counts)
    return counts


if __name__ == "__main__":
    target = Path(sys.argv[1]) if len(sys.argv) > 1 else OUT
    make(target)
    for trial, c in check(target).items():
        print(f"{trial}: rest / rotation / linear acceleration / vibration = {' / '.join(map(str, c))}")
