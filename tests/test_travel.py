"""What could set VQF's time constants on a sensor it never saw (togglecf.run.travel, pipelines/travel.py):
the halves, the reference-free scores on exact synthetic data, and rows that choose only on what they may see."""
import importlib
import json
import math
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from togglecf import simulate
from togglecf.core import quaternion as quat
from togglecf.run.travel import (
    DEFAULT_PAIR,
    FIELD_CHANGE_SCALES,
    TRIAL_STATISTICS,
    choose_pairs,
    field_change_on,
    gyro_steps,
    halves,
    leave_dataset_out,
    pair_on,
    prediction_scores,
    split_rule,
)

REPO = Path(__file__).resolve().parents[1]
PAIRS = [(1.0, 9.0), DEFAULT_PAIR, (3.0, 30.0)]


def test_halves_split_the_scored_samples_at_their_middle():
    movement = np.zeros(20, bool)
    movement[[2, 3, 5, 8, 9, 15]] = True
    first, second = halves(movement)
    assert np.flatnonzero(first).tolist() == [2, 3, 5] and np.flatnonzero(second).tolist() == [8, 9, 15]
    assert not (first & second).any() and ((first | second) == movement).all()
    none = halves(np.zeros(5, bool))
    assert not none[0].any() and not none[1].any()


def _turning_trial():
    """Exact signals (no noise) of a smooth random rotation at 100 Hz for 20 s."""
    q = simulate.random_smooth_trajectory(100.0, 20.0, max_rate=1.5, seed=3)
    return simulate.imu_from_orientation(q, 100.0)


def test_prediction_scores_are_zero_for_the_truth_and_the_offset_squared_for_a_heading_error():
    t = _turning_trial()
    steps = gyro_steps(t, 1.0)
    everywhere = np.ones(t.gyr.shape[0], bool)
    acc_score, mag_score = prediction_scores(t.opt_quat, t, steps, everywhere)
    # the gyroscope's chained increments equal the true rotation between samples (first-order at 100 Hz
    # over 1 s: a few 1e-3 rad at most, squared below 1e-5 rad²)
    assert acc_score < 1e-5 and mag_score < 1e-5
    # the estimate turned 10° about up: gravity is unchanged, north seen 10° off in every sample
    off = quat.multiply(quat.from_rotvec(np.array([0.0, 0.0, math.radians(10.0)])), t.opt_quat)
    acc_off, mag_off = prediction_scores(off, t, steps, everywhere)
    assert acc_off < 1e-5
    assert mag_off == pytest.approx(math.radians(10.0) ** 2, rel=0.02)
    # tilted by 5° about east: gravity is seen 5° off
    tilt = quat.multiply(quat.from_rotvec(np.array([math.radians(5.0), 0.0, 0.0])), t.opt_quat)
    assert prediction_scores(tilt, t, steps, everywhere)[0] == pytest.approx(math.radians(5.0) ** 2, rel=0.02)
    # no sample in the mask: no score
    assert all(math.isnan(s) for s in prediction_scores(t.opt_quat, t, steps, np.zeros_like(everywhere)))


def _record(whole, first, second, stat=0.0, score=(0.0, 0.0, 0.0), field_change=None):
    """A trial's record; ``field_change``: its (whole, second) RMSEs per σ_f (default: every σ_f as off, VQF's
    pair, PAIRS[1])."""
    k = len(FIELD_CHANGE_SCALES)
    whole_fc, second_fc = field_change or ([whole[1]] * k, [second[1]] * k)
    return {"whole": list(whole), "first": list(first), "second": list(second), "score_acc": list(score),
            "score_mag": [0.0] * 3, "stats": {k: stat for k in TRIAL_STATISTICS}, "groups": [],
            "field_change": {"whole": list(whole_fc), "first": list(whole_fc), "second": list(second_fc)}}


def test_rows_choose_only_on_what_they_may_see():
    """Dataset a prefers pair 0 on its whole trials; the test trial of b prefers pair 2 on its first half
    and pair 0 on its second. TAGP is a's choice whatever b's numbers; the first-half row takes b's first
    half; only the oracle looks at the second half."""
    records = {f"a/{k}": _record([1.0, 2.0, 3.0], [1, 2, 3], [1, 2, 3]) for k in range(4)}
    records["b/x"] = _record([3.0, 2.0, 1.0], [3.0, 2.0, 1.0], [1.0, 2.0, 3.0], score=(5.0, 4.0, 0.1))
    rows, rules = choose_pairs(records, [n for n in records if n.startswith("a/")], ["b/x"], PAIRS)
    assert rows["tagp_other"]["b/x"] == 0 and rules["tagp_other"] == list(PAIRS[0])
    assert rows["defaults"]["b/x"] == PAIRS.index(DEFAULT_PAIR)
    assert rows["first_half_reference"]["b/x"] == 2
    assert rows["self_tuned"]["b/x"] == 2
    assert rows["trial_oracle"]["b/x"] == 0
    changed = dict(records, **{"b/x": _record([0.1, 9.0, 9.0], [3.0, 2.0, 1.0], [1.0, 2.0, 3.0])})
    assert choose_pairs(changed, [n for n in records if n.startswith("a/")], ["b/x"], PAIRS)[0]["tagp_other"] == rows[
        "tagp_other"]
    left = leave_dataset_out(records, PAIRS)
    assert left["b"]["rows"]["trial_oracle"]["b/x"]["total"] == 1.0
    assert left["b"]["rows"]["first_half_reference"]["b/x"]["total"] == 3.0


def test_split_rule_finds_the_statistic_that_separates_the_preferences():
    """Low-statistic trials prefer pair 0, high ones pair 2, each losing more on the other's pair than it
    gains on its own (ln 0.75 + ln 2 > 0): one pair for all keeps VQF's defaults; the split at the median
    separates the two."""
    records = {}
    for k in range(8):
        low = k < 4
        whole = [1.5, 2.0, 4.0] if low else [4.0, 2.0, 1.5]
        records[f"a/{k}"] = _record(whole, whole, whole, stat=float(k))
    names = sorted(records)
    assert pair_on(records, names, PAIRS) == 1  # one pair for all: the defaults are the best compromise
    rule = split_rule(records, names, "gyr_rms", PAIRS)
    assert rule["threshold"] == pytest.approx(3.5) and (rule["low"], rule["high"]) == (0, 2)
    assert pair_on(records, [], PAIRS) == PAIRS.index(DEFAULT_PAIR)


def test_field_change_row_takes_the_scale_best_on_the_other_datasets():
    """Dataset a's trials are best at the second σ_f (10 µT) on their whole trials, b's trial at σ_f 0: b left
    out is scored at a's choice on its second half, a left out at b's (off: VQF's own pair's value)."""
    assert FIELD_CHANGE_SCALES[:2] == (0.0, 10.0)
    k = len(FIELD_CHANGE_SCALES)
    a_fc = ([2.0, 1.0] + [1.5] * (k - 2), [2.0, 1.1] + [1.6] * (k - 2))
    records = {f"a/{i}": _record([2.0, 2.0, 2.0], [2.0] * 3, [2.0] * 3, field_change=a_fc) for i in range(3)}
    records["b/x"] = _record([1.0, 1.0, 1.0], [1.0] * 3, [3.0, 3.0, 3.0],
                             field_change=([1.0] + [5.0] * (k - 1), [3.0, 1.2] + [2.5] * (k - 2)))
    left = leave_dataset_out(records, PAIRS)
    assert left["b"]["rules"]["field_change_other"] == 10.0
    assert left["b"]["rows"]["field_change_other"]["b/x"]["total"] == 1.2
    assert left["a"]["rules"]["field_change_other"] == 0.0
    assert left["a"]["rows"]["field_change_other"]["a/0"]["total"] == left["a"]["rows"]["defaults"]["a/0"]["total"]
    assert field_change_on(records, []) == 0


@pytest.mark.slow
def test_quick_run_on_two_datasets_writes_the_table(mini_index, tmp_path):
    """Two copies of the mini trials as two datasets: the script writes a table whose every left-out row
    is scored on every trial and that names its command."""
    dirs = []
    for name in ("one", "two"):
        shutil.copytree(mini_index.root, tmp_path / name)
        dirs.append(tmp_path / name)
    out = tmp_path / "out"
    cmd = [sys.executable, str(REPO / "pipelines" / "travel.py"), "--quick", "--jobs", "1", "--out", str(out)]
    for d in dirs:
        cmd += ["--data", str(d)]
    subprocess.run(cmd, check=True, capture_output=True, text=True, cwd=tmp_path)
    table = (out / "travel.md").read_text()
    assert "python pipelines/travel.py" in table.splitlines()[0]
    assert "## Left out: one" in table and "## Left out: two" in table
    result = json.loads((out / "travel.json").read_text())
    n = len(mini_index.available)
    for ds in ("one", "two"):
        rows = result["left_out"][ds]["rows"]
        assert all(len(per) == n for per in rows.values()) and "field_change_other" in rows
        # the oracle is at least as good as every row of a pair on every trial (the field-change row is not one)
        for row, per in rows.items():
            if row == "field_change_other":
                continue
            assert all(rows["trial_oracle"][k]["total"] <= v["total"] + 1e-12 for k, v in per.items()), row


def test_script_needs_two_datasets(tmp_path, mini_index, capsys):
    sys.path.insert(0, str(REPO / "pipelines"))
    try:
        script = importlib.import_module("travel")
    finally:
        sys.path.remove(str(REPO / "pipelines"))
    with pytest.raises(SystemExit) as exc:
        script.main(["--data", str(mini_index.root), "--out", str(tmp_path)])
    assert exc.value.code == 2 and "at least two datasets" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        script.main(["--data", str(tmp_path / "nowhere"), "--data", str(mini_index.root)])
    assert "no trials.json" in capsys.readouterr().err
