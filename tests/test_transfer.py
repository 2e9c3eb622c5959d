"""The cross-dataset protocol (togglecf.run.transfer, run by `make run`): trained filters and the
classic ones scored on another directory, each study fold's models on its own test trials read
from a decimated copy, and the Markdown table with the fallback share."""
import json
from dataclasses import replace

import numpy as np
import pytest

from conftest import train_tiny_models, with_fixed_gains
from togglecf.data import DatasetIndex
from togglecf.registry import TRAINED
from togglecf.run.transfer import (CLASSIC, decimate_trial, models_transfer, results_json, study_transfer,
                                   transfer_table, write_decimated)
from togglecf.toggling.gains import GainSearch, VQFGainSearch


def _both_kinds(class_names, static_state, use_mag):
    """Fixed (not learned) gains of both learned filters, distinct per state so the models matter."""
    n = len(class_names)
    return (replace(GainSearch().start(class_names, static_state), tau_acc=(0.5, 5.0, 20.0, 60.0, 2.0)[:n]),
            replace(VQFGainSearch().start(class_names), tau_acc_states=(1.0, 3.0, 8.0, 20.0, 2.0)[:n]))


@pytest.fixture(scope="module")
def model_dir(mini_index, tmp_path_factory):
    """Tiny models on two mini trials with fixed gains."""
    return with_fixed_gains(train_tiny_models(mini_index.root, "02,07", tmp_path_factory.mktemp("transfer") / "m"),
                            _both_kinds, ["02", "07"])


def test_decimate_trial_averages_blocks(mini_trial):
    d = decimate_trial(mini_trial, 3)
    n = mini_trial.n_samples // 3
    assert d["imu_gyr"].shape == (n, 3)
    np.testing.assert_allclose(d["imu_acc"][4], mini_trial.acc[12:15].mean(axis=0))
    np.testing.assert_array_equal(d["opt_quat"][4], mini_trial.opt_quat[14])  # the block's last sample
    with pytest.raises(ValueError, match=">= 2"):
        decimate_trial(mini_trial, 1)


def test_models_on_another_directory_and_the_table(model_dir, mini_index, tmp_path):
    slow = DatasetIndex.from_dir(write_decimated(mini_index, tmp_path / "slow", 3))
    per = models_transfer(model_dir, slow)
    assert list(per) == [*TRAINED, *CLASSIC]
    names = sorted(slow.available)
    for f, res in per.items():
        assert sorted(res) == names and all(np.isfinite(r.errors["total"]) for r in res.values())
        assert ("fallback" in next(iter(res.values())).diagnostics) == (f in TRAINED)  # only the learned filters
    text = transfer_table(per, slow, "what", "cmd")
    rows = [ln for ln in text.splitlines() if ln.startswith("| ") and not ln.startswith("| filter")]
    assert [r.split(" | ")[0][2:] for r in rows] == list(per)
    mean = np.mean([r.errors["total"] for r in per["vqf_core"].values()])
    assert f"| vqf_core | {mean:.2f} |" in text  # the table's number is the mean of the trials' errors
    assert rows[0].rstrip(" |").endswith("%") and not rows[-1].rstrip(" |").endswith("%")
    # the toggling CF also reports its low-confidence share (a diagnostic of its confidence floor)
    assert [r.count("%") for r in rows[:2]] == [2, 1] and TRAINED[:2] == ("toggling", "vqf_toggling")
    json.dumps(results_json(per))


def test_study_transfer_uses_each_folds_own_models(model_dir, mini_index, tmp_path):
    """Two 'folds' with different models: each test trial is scored with its fold's models (the
    result equals scoring it with that model directory directly)."""
    study = tmp_path / "study"
    other = with_fixed_gains(train_tiny_models(mini_index.root, "07,24", tmp_path / "other"), _both_kinds, ["07", "24"])
    names = sorted(mini_index.available)
    for k, d in enumerate((model_dir, other)):
        (study / "folds" / f"fold{k}").mkdir(parents=True)
        (study / "folds" / f"fold{k}" / "models").symlink_to(d)
    (study / "results.json").write_text(json.dumps({"folds": [{"fold": 0, "test": [names[2]]},
                                                              {"fold": 1, "test": names[:2]}]}))
    per = study_transfer(study, mini_index)
    direct = models_transfer(other, mini_index, trials=",".join(n[:2] for n in names[:2]))
    own = models_transfer(model_dir, mini_index, trials=names[0][:2])
    for f in TRAINED:
        for n in names[:2]:
            assert per[f][n].errors == direct[f][n].errors
        assert own[f][names[0]].errors != per[f][names[0]].errors  # the other fold's models would differ
    (study / "results.json").write_text(json.dumps({"folds": [{"fold": 0, "test": ["99_not_in_this_directory"]}]}))
    with pytest.raises(ValueError, match="none of the test trials"):
        study_transfer(study, mini_index)
