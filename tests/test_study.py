"""The held-out study on 4 real trials with tiny models: the report is complete and the
protocol is honest (no test trial in any fold's model training or gain learning; baselines
take their TAGP on the training trials only)."""
import json

import numpy as np
import pandas as pd
import pytest

from conftest import TINY_TRAIN_TOML
from togglecf.run.sweep import evaluate_trials
from togglecf.learn.folds import trial_folds
from togglecf.run.study import load_study_config, run_study

pytestmark = pytest.mark.broad

TRAIN = TINY_TRAIN_TOML

STUDY = """
[study]
folds = 2
train_config = "train.toml"
ablations = ["toggling_only", "noise_only", "6d", "vqf_taus_only", "vqf_oracle", "madgwick_rest_bias"]
[baselines.cf]
tau = [17.5, 11.66, 0.3482]
[baselines.madgwick]
beta = [0.05, 0.1]
[baselines_6d.cf]
tau = [17.5, 11.66]
"""


def test_trial_folds_partition():
    names = [f"{i:02d}_x" for i in range(25)]
    folds = trial_folds(names, 5)
    assert sorted(sum(folds, [])) == sorted(names) and all(len(f) == 5 for f in folds)
    with pytest.raises(ValueError):
        trial_folds(names[:3], 4)


def test_study_report_and_no_leakage(broad_index, tmp_path):
    (tmp_path / "train.toml").write_text(TRAIN)
    (tmp_path / "study.toml").write_text(STUDY)
    out = tmp_path / "report"
    res = run_study(load_study_config(tmp_path / "study.toml"), data_dir=broad_index.root, out_dir=out,
                    trials="02,07,24,29")
    for f in ("summary.md", "per_trial.csv", "per_trial_total.csv", "per_group.csv", "results.json", "plots/groups.png",
              "plots/error_07_undisturbed_fast_rotation_B.png", "plots/timeline_24_disturbed_tapping_A.png"):
        assert (out / f).is_file(), f
    df = pd.read_csv(out / "per_trial.csv")
    for filt in ("toggling", "cf", "madgwick", "toggling_only", "noise_only", "toggling_6d", "cf_6d", "vqf_toggling",
                 "vqf_core_defaults", "vqf_taus_only", "vqf_oracle", "madgwick_rest_bias"):
        assert sorted(df[df["filter"] == filt]["trial"]) == sorted(res["trials"]), filt
    for fold in res["folds"]:
        model_dir = out / "folds" / f"fold{fold['fold']}" / "models"
        meta = json.loads((model_dir / "metadata.json").read_text())
        gains = json.loads((model_dir / "gains.json").read_text())
        assert not set(fold["test"]) & set(meta["training_trials"])
        assert not set(fold["test"]) & set(gains["9d"]["trials"])
        assert not set(fold["test"]) & set(gains["vqf_9d"]["trials"])  # the learned VQF time constants too
        # the baseline's fold TAGP is the grid point with the lowest mean over the training trials
        cf_rows = pd.read_csv(out / "per_trial.csv")
        params = json.loads(cf_rows[(cf_rows["filter"] == "cf") & (cf_rows["fold"] == fold["fold"])]["params"].iloc[0])
        assert params == fold["baseline_tagp"]["cf"]["params"]
        grid = [{"tau": t} for t in (17.5, 11.66, 0.3482)]  # recomputed independently on the training trials
        res_train = evaluate_trials(broad_index, fold["train"], "cf", grid, jobs=1)
        means = [np.mean([r[n].errors["total"] for n in fold["train"]]) for r in res_train]
        assert params == grid[int(np.argmin(means))]
    per_group = pd.read_csv(out / "per_group.csv", index_col=[0, 1])
    assert {"total", "heading", "inclination", "roll", "pitch", "yaw", "us_per_sample"} <= set(per_group.index.get_level_values(0))
    summary = (out / "summary.md").read_text()
    assert "Δ madgwick" in summary and "Ablations" in summary
    assert f"({len(res['trials'])} BROAD trials, 9D)" in summary.splitlines()[0]  # one dataset: no dataset names
