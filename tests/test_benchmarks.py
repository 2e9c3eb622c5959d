"""Benchmarks that cannot rot: every ``pipelines/bench_*.py`` runs its ``--quick`` mode here (seconds,
on the mini data: the BROAD cuts in ``tests/data/broad_mini``, made from BROAD on first use, or without
BROAD the synthetic trials in ``tests/data/synthetic_mini``), measures against VQF in the same run and
writes its table (Markdown + CSV) where ``--out`` says."""
import csv
import importlib
import math
import sys
from pathlib import Path

import pytest

from togglecf.embedded import cycles

PIPELINES = Path(__file__).resolve().parents[1] / "pipelines"
#: benchmark -> extra quick-mode arguments and the ratio names its result must hold
BENCHES = {
    "bench_vqf_core": ([], ["vqf_core 9D", "vqf_core 6D"]),
    "bench_filters": ([], ["madgwick 9D", "cf 6D", "vqf_core 9D", "ekf 9D"]),
    "bench_features": ([], ["features"]),
    "bench_toggling": ([], ["toggling, models in the loop", "toggling core, predictions given"]),
    "bench_learned_vqf": ([], ["LearnedVQF / vqf_core", "models in the loop, learning on: τ_acc per state",
                              "LearnedVQF as shipped (its learned settings)",
                              "LearnedVQF as shipped (its learned settings), at a phone's rate (every 3 samples "
                              "averaged)",
                              "models in the loop, learning on: τ_acc per state, at a phone's rate (every 3 samples "
                              "averaged)"]),
    "bench_dask": ([], ["dask, 1 worker process(es)", "mahony serial"]),
    "bench_cycles": (["--samples", "40"], ["VQF core 6D (tcf_vqf.c) -O2", "learned VQF 9D, pretrained model -O2"]),
}


def _load(name):
    sys.path.insert(0, str(PIPELINES))
    try:
        return importlib.import_module(name)
    finally:
        sys.path.remove(str(PIPELINES))


def test_every_benchmark_is_run_here():
    found = {p.stem for p in PIPELINES.glob("bench_*.py")} - {"bench_common"}
    assert found == set(BENCHES), "a benchmark without a quick-mode test: add it to BENCHES"


@pytest.mark.parametrize("name", sorted(BENCHES))
def test_quick_mode_runs_and_writes_its_table(name, tmp_path, capsys, mini_index):
    if name == "bench_dask":
        pytest.importorskip("distributed")
    if name == "bench_cycles" and cycles.missing_reason() is not None:
        pytest.skip(f"cycle estimate unavailable: {cycles.missing_reason()}")
    extra, ratio_names = BENCHES[name]
    mod = _load(name)
    res = mod.main(["--quick", "--out", str(tmp_path / name), *extra])
    out = capsys.readouterr().out
    for r in ratio_names:
        assert r in res["ratios"], (r, sorted(res["ratios"]))
        assert math.isfinite(res["ratios"][r]) and res["ratios"][r] > 0
    md, cv = tmp_path / f"{name}.md", tmp_path / f"{name}.csv"
    assert res["paths"] == {"md": md, "csv": cv}
    text = md.read_text()
    assert text.startswith("# ") and "ratio_to_vqf" in text and "quick mode" in text and "vqf" in text
    with open(cv, newline="") as f:
        rows = list(csv.DictReader(f))
    assert len(rows) == len(res["rows"]) >= 2 and "ratio_to_vqf" in rows[0]
    assert "ratio_to_vqf" in out  # the table is printed too


def test_quick_mode_without_out_writes_nothing(tmp_path, monkeypatch, mini_index):
    mod = _load("bench_vqf_core")
    monkeypatch.setattr(sys.modules["bench_common"], "BENCH_DIR", tmp_path / "reports")
    res = mod.main(["--quick", "--repeats", "1"])
    assert res["paths"] == {} and not (tmp_path / "reports").exists()
    assert res["ratio"] == pytest.approx(res["core_us"] / res["vqf_us"])


def test_round_ratios_pair_each_round_with_its_own_reference():
    """Each round's time over the reference's in the same round (not the ratio of the best times): a round
    where the machine was slow for both gives the same ratio as a fast one."""
    common = _load("bench_common")
    times = {"loop": [2.0, 3.0, 4.0], "vqf": [1.0, 2.0, 2.0]}
    assert common.round_ratios(times, "loop", "vqf") == (1.5, 2.0, 2.0)
    calls = []
    got = common.interleaved_times({"a": lambda: calls.append("a"), "b": lambda: calls.append("b")}, 2)
    assert calls == ["a", "b"] * 3  # a warm-up round, then the rounds alternate
    assert [len(v) for v in got.values()] == [2, 2]
