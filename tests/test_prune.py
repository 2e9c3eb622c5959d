"""The pruning sweep (togglecf.run.prune) and `togglecf export --max-bytes`."""
import json
import shutil

import numpy as np
import pytest

from conftest import TINY_TRAIN_TOML
from togglecf.run import prune
from togglecf.run.prune import PrunePoint


def _row(key, size, err, reference=False):
    return {"key": key, "array_riscv_bytes": size, "mean_total": err, "reference": reference}


def test_pareto_front_keeps_only_undominated_rows():
    rows = [_row("a", 10, 3.0), _row("b", 20, 2.5), _row("c", 30, 2.8), _row("d", 40, 2.0), _row("e", 50, 2.0),
            _row("f", None, 1.0)]
    # c is beaten by b (smaller and better), e by d (same error, larger), f has no size
    assert [r["key"] for r in prune.pareto_front(rows)] == ["a", "b", "d"]


def test_choose_point_takes_the_most_accurate_within_the_budget():
    rows = [_row("a", 10, 3.0), _row("b", 20, 2.5), _row("c", 30, 2.8), _row("d", 40, 2.0)]
    assert prune.choose_point(rows, 35)["key"] == "b"
    assert prune.choose_point(rows, 40)["key"] == "d"  # the budget is inclusive
    with pytest.raises(ValueError, match="smallest is a with 10 bytes"):
        prune.choose_point(rows, 9)


def test_tie_verdicts_against_the_reference():
    """A point whose per-trial errors move by less than their spread around the reference's is a
    tie (Wilcoxon p >= 0.05); one worse on all 25 trials is worse; rows without per-trial errors
    get no verdict."""
    rng = np.random.default_rng(0)
    base = {f"t{i:02d}": 2.0 + rng.random() for i in range(25)}
    noisy = {k: v + rng.normal(0.0, 0.3) for k, v in base.items()}  # no systematic shift
    worse = {k: v + 0.2 + 0.01 * i for i, (k, v) in enumerate(base.items())}  # every trial worse
    rows = [{**_row("ref", 50, 2.5, reference=True), "trial_totals": base},
            {**_row("noisy", 20, 2.5), "trial_totals": noisy}, {**_row("worse", 10, 2.8), "trial_totals": worse},
            _row("old", 30, 2.4)]
    v = {r["key"]: (r["vs_reference"], r["p_vs_reference"]) for r in prune.tie_verdicts(rows)}
    assert v["ref"] == ("reference", None) and v["old"] == ("", None)
    assert v["noisy"][0] == "tie" and v["noisy"][1] >= 0.05
    assert v["worse"][0] == "worse" and v["worse"][1] < 1e-4  # 25 of 25 positive differences
    full = [{**r, "features_used": 74, "us_per_prediction": 1.0} for r in rows]
    text = prune.format_front(full)
    assert "vs ref" in text and "tie p=" in text


def test_points_apply_to_a_config_copy_and_the_grid_runs_the_reference_once():
    cfg = {"run": {"max_features": 0, "seed": 0}, "classifier": {"n_estimators": 10, "max_depth": 3},
           "regressor": {"n_estimators": 10, "max_depth": 3}}
    pts = prune.default_points(cfg, trees=(10, 20), depths=(3,), features=(0, 8))
    assert pts[0].reference and pts[0].key == "c10x3_r10x3_fall"
    assert [p.key for p in pts] == ["c10x3_r10x3_fall", "c10x3_r10x3_f8", "c20x3_r20x3_fall", "c20x3_r20x3_f8"]
    new = PrunePoint(5, 2, 4, 3, 12).apply(cfg)
    assert new["classifier"] == {"n_estimators": 5, "max_depth": 2}
    assert new["regressor"] == {"n_estimators": 4, "max_depth": 3} and new["run"]["max_features"] == 12
    assert cfg["classifier"]["n_estimators"] == 10 and cfg["run"]["max_features"] == 0  # untouched


# ------------------------------------------------------- real trials: the shipped mini BROAD cuts

POINTS = [PrunePoint(8, 3, 4, 3, 0, True), PrunePoint(3, 2, 3, 2, 6)]
#: held-out folds of the sweep: leave-one-trial-out over the 3 mini trials. (It was 2 folds over
#: 4 full trials; 2 folds of 3 trials would leave one fold a single training trial, which the 2
#: inner folds of the gain search cannot split by trial.)
FOLDS = 3


@pytest.fixture(scope="module")
def tiny_sweep(mini_index, tmp_path_factory):
    """A model directory trained on the 3 mini trials with a tiny config, and a 2-point sweep of
    it (3 held-out folds, 2 inner folds); the log lines are kept to count computed points."""
    from togglecf.run.train import run_training

    root = tmp_path_factory.mktemp("prune")
    (root / "tiny.toml").write_text(TINY_TRAIN_TOML)
    run_training(str(root / "tiny.toml"), data_dir=mini_index.root, trials="02,07,24", out=root / "models",
                 cv=True, verbose=False)
    logs = []
    rows = prune.pruning_sweep(root / "models", root / "sweep", POINTS, folds=FOLDS, inner_folds=2,
                               data_dir=mini_index.root, riscv=False, log=logs.append)
    return root, rows, logs


@pytest.mark.slow
def test_sweep_reference_equals_an_independent_held_out_run(tiny_sweep, mini_index):
    """The sweep reuses one dataset for all folds and points; the reference point must give the
    same per-trial errors as training each fold from scratch (run_training on the fold's trials)
    and filtering its test trials: the same protocol as the study, computed the slow way."""
    from togglecf.metrics.broad import trial_errors
    from togglecf.toggling import load_toggling_filter
    from togglecf.run.study import trial_folds
    from togglecf.run.config import load_config
    from togglecf.run.train import run_training

    root, rows, _ = tiny_sweep
    rec = [json.loads(line) for line in (root / "sweep" / "sweep_rows.jsonl").read_text().splitlines()]
    got = {r["trial"]: r["total"] for r in rec[0]["per_trial"]}
    cfg = load_config(str(root / "tiny.toml"))
    cfg["gains"].update(learn=True, modes=["9d"])
    cfg["run"]["cv_folds"] = 2
    names = mini_index.select("02,07,24")
    expected = {}
    for k, test in enumerate(trial_folds(names, FOLDS)):
        train = [n for n in names if n not in test]
        out = root / f"independent{k}"
        run_training(cfg, data_dir=mini_index.root, trials=",".join(train), out=out, cv=True, verbose=False)
        for n in test:
            t = mini_index.load(n)
            o = load_toggling_filter(out, t.fs).update_batch(t.gyr, t.acc, t.mag)
            expected[n] = trial_errors(o.quat, t.opt_quat, t.movement)["total"]
    assert got.keys() == expected.keys()
    for n in names:  # same data, seeds and code path: equal to rounding
        assert got[n] == pytest.approx(expected[n], rel=1e-9), n
    assert rows[0]["mean_total"] == pytest.approx(np.mean(list(expected.values())), rel=1e-9)


@pytest.mark.slow
def test_sweep_rows_sizes_and_feature_limit(tiny_sweep):
    _, rows, _ = tiny_sweep
    ref, small = rows
    assert ref["reference"] and not small["reference"]
    assert small["features_used"] <= 6 < ref["features_used"]  # max_features = 6 is obeyed by every tree
    assert small["array_host_bytes"] < ref["array_host_bytes"]
    for r in rows:
        assert 0.0 < r["mean_total"] < 20.0 and r["max_total"] >= r["mean_total"]
        assert r["us_per_prediction"] > 0 and r["tl2cgen_host_bytes"] > 0
        assert r["array_riscv_bytes"] is None  # riscv=False


@pytest.mark.slow
def test_sweep_resumes_with_only_the_missing_points(tiny_sweep, mini_index):
    root, rows, logs = tiny_sweep
    assert sum("[1/2]" in m or "[2/2]" in m for m in logs) == 2
    logs2 = []
    more = POINTS + [PrunePoint(2, 2, 2, 2, 0)]
    rows2 = prune.pruning_sweep(root / "models", root / "sweep", more, folds=FOLDS, inner_folds=2,
                                data_dir=mini_index.root, riscv=False, log=logs2.append)
    assert "(2 already done" in logs2[0]
    assert [m.split(":")[0] for m in logs2 if m.startswith("[")] == ["[1/1] c2x2_r2x2_fall"]  # only the new one
    assert rows2[:2] == rows
    paths = prune.write_sweep_report(rows2, root / "sweep", "array_host_bytes", max_bytes=10**6)
    import pandas as pd

    df = pd.read_csv(paths["sweep"])
    assert len(df) == 3 and df["pareto"].any() and paths["plot"].stat().st_size > 1000
    assert len(pd.read_csv(paths["pareto"])) == int(df["pareto"].sum())


@pytest.mark.slow
def test_export_max_bytes_trains_and_exports_the_chosen_point(tiny_sweep, mini_index, tmp_path):
    """`togglecf export --max-bytes`: resumes the sweep (no point recomputed), picks the most
    accurate point within the budget, trains it on the model's training trials and exports it."""
    from togglecf.cli.main import main

    root, rows, _ = tiny_sweep
    budget = max(r["array_host_bytes"] for r in rows) - 1  # only the small point fits (host sizes: --no-riscv)
    # the sweep of POINTS alone: another test adds a smaller point to the shared sweep directory,
    # and which of two points that fit is more accurate is not what this test is about
    sweep = tmp_path / "sweep"
    shutil.copytree(root / "sweep", sweep)
    keys = {p.key for p in POINTS}
    lines = (sweep / "sweep_rows.jsonl").read_text().splitlines()
    (sweep / "sweep_rows.jsonl").write_text("".join(f"{ln}\n" for ln in lines
                                                    if json.loads(ln)["row"]["key"] in keys))
    out = tmp_path / "emb"
    rc = main(["export", "--models", str(root / "models"), "--out", str(out), "--max-bytes", str(budget),
               "--sweep", str(sweep), "--trees", "3", "--depths", "2", "--features", "6", "--folds", str(FOLDS),
               "--inner-folds", "2", "--data", str(mini_index.root), "--no-riscv", "--format", "array",
               "--trials", "07"])
    assert rc == 0
    rep = json.loads((out / "export_report.json").read_text())
    assert rep["pruning"]["point"]["key"] == "c3x2_r3x2_f6"
    meta = json.loads((out / "models" / "metadata.json").read_text())
    assert meta["config"]["classifier"]["n_estimators"] == 3 and meta["config"]["run"]["max_features"] == 6
    assert meta["training_trials"] == json.loads((root / "models" / "metadata.json").read_text())["training_trials"]
    assert (out / "models" / "gains.json").is_file() and rep["array"]["ok"]


# ------------------------------------------- export --max-bytes without a sweep: the default point


def _fake_training(calls, source_dir):
    """Stands in for ``run_training`` in ``togglecf export``: records the config, copies trained models."""
    import shutil

    def fake(cfg, data_dir=None, trials=None, out=None, **kw):
        calls.append({"cfg": cfg, "trials": trials, "out": out})
        shutil.copytree(source_dir, out, dirs_exist_ok=True)
        return {"out": out}
    return fake


def test_export_max_bytes_without_sweep_uses_the_default_point(tiny_model_dir, mini_index, tmp_path, monkeypatch,
                                                                capsys):
    """No sweep in --sweep/OUT/sweep: the documented default point is trained (no sweep runs); a budget
    below its measured size is refused at once; --full-sweep runs the sweep."""
    from togglecf.cli import export as cli_export
    from togglecf.cli.main import main

    calls = []
    monkeypatch.setattr(cli_export, "run_training", _fake_training(calls, tiny_model_dir))
    monkeypatch.setattr(cli_export, "sweep_from_args", lambda *a, **k: pytest.fail("the sweep must not run"))
    assert prune.DEFAULT_EXPORT_POINT == PrunePoint(10, 4, 10, 4, 0)
    out = tmp_path / "emb"
    args = ["export", "--models", str(tiny_model_dir), "--out", str(out), "--data", str(mini_index.root),
            "--no-riscv", "--no-check", "--format", "array"]
    assert main([*args, "--max-bytes", "32768"]) == 0
    assert len(calls) == 1
    cfg = calls[0]["cfg"]
    assert cfg["classifier"]["n_estimators"] == 10 and cfg["classifier"]["max_depth"] == 4
    assert cfg["regressor"]["n_estimators"] == 10 and cfg["regressor"]["max_depth"] == 4
    assert cfg["run"]["max_features"] == 0
    rep = json.loads((out / "export_report.json").read_text())
    assert rep["pruning"]["source"] == "default" and rep["pruning"]["point"]["key"] == "c10x4_r10x4_fall"
    assert "no pruning sweep in" in capsys.readouterr().err
    # a budget the default point cannot meet: refused before any training
    assert main([*args, "--max-bytes", "8000"]) == 1
    err = capsys.readouterr().err
    assert (f"below the default pruned point's {prune.DEFAULT_EXPORT_SIZES['array_host_bytes']} bytes" in err
            and "--full-sweep" in err and len(calls) == 1)
    # --full-sweep: the sweep runs (here: stubbed to one row) and its best point is trained
    row = {"key": "c3x2_r3x2_f6", "clf_trees": 3, "clf_depth": 2, "reg_trees": 3, "reg_depth": 2, "max_features": 6,
           "reference": False, "features_used": 6, "mean_total": 3.0, "array_host_bytes": 5000,
           "array_riscv_bytes": 5000, "us_per_prediction": 0.5}
    monkeypatch.setattr(cli_export, "sweep_from_args", lambda a, d: [row])
    assert main([*args, "--max-bytes", "8000", "--full-sweep"]) == 0
    assert calls[-1]["cfg"]["classifier"]["n_estimators"] == 3
    assert json.loads((out / "export_report.json").read_text())["pruning"]["source"] == "sweep"
