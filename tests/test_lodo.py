"""Leave one dataset out (togglecf.run.lodo, `make run` step 4) and the gain search's objective that
no dataset can dominate (togglecf.toggling.gains.objective_value)."""
import math
import shutil

import numpy as np
import pytest

from togglecf.run.config import load_config
from togglecf.run.lodo import CORE_OF, ROWS, dataset_dirs, leave_one_dataset_out, lodo_json, lodo_table
from togglecf.toggling import gains as gains_module
from togglecf.toggling.gains import VQFGainSearch, learn_gains, objective_value, step_margin, trial_datasets


def test_worst_dataset_log_ratio_by_hand():
    # dataset a: ratios 0.5 and 2 -> mean ln = 0; dataset b: ratio 1.1 on its one trial -> ln 1.1
    start = np.array([2.0, 1.0, 10.0])
    rmse = np.array([1.0, 2.0, 11.0])
    ds = np.array(["a", "a", "b"])
    worst = objective_value("worst_dataset_log_ratio", rmse, start, ds)
    assert worst == pytest.approx(math.log(1.1) + 1e-3 * 0.5 * (0.0 + math.log(1.1)))
    assert objective_value("mean_rmse", rmse, start, ds) == pytest.approx(14.0 / 3)
    # at the start every ratio is 1: the objective is 0, and a change that helps one dataset by 20 % but
    # hurts the other by 1 % is worse than the start (the mean RMSE would have taken it)
    assert objective_value("worst_dataset_log_ratio", start, start, ds) == 0.0
    trade = np.array([1.6, 0.8, 10.1])
    assert objective_value("worst_dataset_log_ratio", trade, start, ds) > 0.0
    assert objective_value("mean_rmse", trade, start, ds) < objective_value("mean_rmse", start, start, ds)
    # a trial without a scored sample (NaN) is left out, not a NaN objective
    assert np.isfinite(objective_value("worst_dataset_log_ratio", np.array([1.0, np.nan, 11.0]), start, ds))
    with pytest.raises(ValueError, match="objective"):
        objective_value("median", rmse, start, ds)


def test_mean_dataset_log_ratio_by_hand():
    # dataset a: ratios 0.8 and 0.9 -> mean ln(0.8·0.9)/2; dataset b: ratio 1 on its trial -> 0
    start = np.array([2.0, 1.0, 10.0])
    helps_a = np.array([1.6, 0.9, 10.0])
    mean_a = 0.5 * (math.log(0.8) + math.log(0.9))
    assert objective_value("mean_dataset_log_ratio", helps_a, start, ["a", "a", "b"]) == pytest.approx(0.5 * mean_a)
    # the worst dataset's objective refuses that step (b gains nothing; only the 1e-3 tie-break moves)
    assert objective_value("worst_dataset_log_ratio", helps_a, start, np.array(["a", "a", "b"])) == pytest.approx(
        1e-3 * 0.5 * mean_a)
    # no dataset may end above learning off, however much the other gains: +inf
    trade = np.array([1.0, 0.5, 10.1])
    assert objective_value("mean_dataset_log_ratio", trade, start, np.array(["a", "a", "b"])) == math.inf
    # one dataset: its mean, as the worst dataset's objective without the tie-break
    one = np.array(["a", "a", "a"])
    assert objective_value("mean_dataset_log_ratio", helps_a, start, one) == pytest.approx(
        np.mean(np.log(helps_a / start)))
    # its step margin: the SE of the mean of the per-dataset means, √(SE_a² + SE_b²) / 2
    current = np.full(6, 2.0)
    ch = np.array([-0.1, 0.0, 0.1, -0.02, 0.0, 0.02])
    ds = np.array(["a"] * 3 + ["b"] * 3)
    se_a, se_b = np.std(ch[:3], ddof=1) / math.sqrt(3), np.std(ch[3:], ddof=1) / math.sqrt(3)
    assert step_margin("one_se", "mean_dataset_log_ratio", current * np.exp(ch), current, ds) == pytest.approx(
        math.sqrt(se_a ** 2 + se_b ** 2) / 2, rel=1e-12)


def test_mean_dataset_objective_keeps_a_step_that_helps_one_dataset_more_than_the_other(monkeypatch):
    """The descent (gains._descend) on made-up RMSEs of two datasets of 6 trials, each step's per-trial change
    scattered by ±2 % (a) and ±0.2 % (b) around its mean: τ_acc[rest] 5 s lowers a's by 10 % and b's by 0.1 %;
    2 s lowers a's by 20 % and raises b's by 1 %. The worst dataset's objective keeps neither (b's 0.1 % is
    within a's scatter, the margin); the mean over datasets keeps 5 s and refuses 2 s (b above learning off)."""
    sign = np.array([1.0, -1.0] * 3)

    def fake_rmse(settings, trials, predictions, use_mag=True, pool=None):
        tau = settings.tau_acc_states[0]
        if tau == 3.0:
            return np.ones(12)
        a, b = (0.9, 0.999) if tau == 5.0 else (0.8, 1.01)
        return np.r_[a * np.exp(0.02 * sign), b * np.exp(0.002 * sign)]

    monkeypatch.setattr(gains_module, "trial_total_rmse", fake_rmse)
    trials = [f"a/{i}" for i in range(6)] + [f"b/{i}" for i in range(6)]
    for objective, expected in (("worst_dataset_log_ratio", 3.0), ("mean_dataset_log_ratio", 5.0)):
        search = VQFGainSearch(tau_acc=(2.0, 3.0, 5.0), confidence_floor=(0.0,), mag_disturbance_scale=(0.0,),
                               sweeps=1, objective=objective)
        settings, _ = learn_gains(trials, [None] * 12, ("rest", "rotation"), None, search=search, memo=None)
        assert settings.tau_acc_states[0] == expected, objective


def test_one_standard_error_margin_by_hand():
    # dataset a: per-trial ln changes -0.1, 0, 0.1, 0 -> SE = std(ddof=1) / 2 = 0.0408; dataset b: all -0.01 -> SE 0
    current = np.full(7, 2.0)
    rmse = current * np.exp([-0.1, 0.0, 0.1, 0.0, -0.01, -0.01, -0.01])
    ds = np.array(["a"] * 4 + ["b"] * 3)
    se_a = np.std([-0.1, 0.0, 0.1, 0.0], ddof=1) / 2.0
    assert step_margin("one_se", "worst_dataset_log_ratio", rmse, current, ds) == pytest.approx(se_a, rel=1e-12)
    assert step_margin("any_gain", "worst_dataset_log_ratio", rmse, current, ds) == 0.0
    # mean_rmse: the SE of the RMSE differences [deg] over all trials, datasets pooled
    diff = rmse - current
    assert step_margin("one_se", "mean_rmse", rmse, current, ds) == pytest.approx(np.std(diff, ddof=1) / math.sqrt(7))
    # one trial per dataset has no scatter to measure: no margin; a NaN trial is left out
    assert step_margin("one_se", "worst_dataset_log_ratio", rmse[:2], current[:2], np.array(["a", "b"])) == 0.0
    assert np.isfinite(step_margin("one_se", "worst_dataset_log_ratio", np.r_[np.nan, rmse[1:]], current, ds))
    with pytest.raises(ValueError, match="step rule"):
        step_margin("best", "mean_rmse", rmse, current, ds)
    with pytest.raises(ValueError, match="step_rule"):
        VQFGainSearch(step_rule="best")


def test_one_se_rule_keeps_the_core_unless_the_gain_beats_the_scatter(monkeypatch):
    """The descent's acceptance (gains._descend) on a made-up objective: trial RMSEs as a function of
    τ_acc[rest] alone. τ 2 s lowers the mean log ratio by 0.01 with a ±0.05 scatter over 10 trials (SE 0.017):
    kept by "any_gain", refused by "one_se"; τ 5 s (when offered) lowers every trial's by 0.1: kept by both."""
    scatter = np.array([0.05, -0.05] * 5)

    def rmse_for(clear_gain_offered: bool):
        def fake_rmse(settings, trials, predictions, use_mag=True, pool=None):
            tau = settings.tau_acc_states[0]
            if tau == 2.0:
                return np.exp(-0.01 + scatter)
            return np.full(10, np.exp(-0.1)) if tau == 5.0 and clear_gain_offered else np.ones(10)
        return fake_rmse

    trials = [f"d/{i}" for i in range(10)]
    states = ("rest", "rotation")
    for clear, rule, expected in ((False, "any_gain", 2.0), (False, "one_se", 3.0), (True, "one_se", 5.0)):
        monkeypatch.setattr(gains_module, "trial_total_rmse", rmse_for(clear))
        search = VQFGainSearch(tau_acc=(2.0, 3.0, 5.0), confidence_floor=(0.0,), mag_disturbance_scale=(0.0,),
                               sweeps=1, step_rule=rule)
        settings, _ = learn_gains(trials, [None] * 10, states, None, search=search, memo=None)
        assert settings.tau_acc_states[0] == expected, (rule, clear)


def test_trial_datasets_from_names():
    class T:
        def __init__(self, name):
            self.name = name

    assert list(trial_datasets([T("broad/01_x"), T("tyrex_nexus5/A_B"), T("05_plain")])) == [
        "broad", "tyrex_nexus5", ""]


def test_dataset_dirs_finds_siblings_in_broads_layout(tmp_path):
    for d in ("broad", "zeta", "alpha", "not_data"):
        (tmp_path / d).mkdir()
    for d in ("broad", "zeta", "alpha"):
        (tmp_path / d / "trials.json").write_text("{}")
    assert [p.name for p in dataset_dirs(tmp_path / "broad")] == ["broad", "alpha", "zeta"]


TINY_LEARNING_OFF = {
    "run": {"cv_folds": 2},
    "classifier": {"n_estimators": 8, "max_depth": 3},
    "regressor": {"n_estimators": 4, "max_depth": 3},
    "gains": {"modes": ["9d", "vqf_9d"], "tau": [11.66], "output_tau": [0.0], "bias_tau": [3.498],
              "bias_gate": [0.05], "mag_disturbance_scale": [0.0], "confidence_floor": [0.0]},
}
#: every learned VQF value at the core's: learning off, whatever the models predict
VQF_OFF = {"tau_acc": [3.0], "tau_mag": [9.0], "confidence_floor": [0.0], "mag_disturbance_scale": [0.0]}


@pytest.mark.slow
def test_leave_one_dataset_out_on_two_datasets(mini_index, tmp_path):
    """Two copies of the mini trials as two datasets, each scored with models trained on the other (the same
    recordings: a test of the plumbing, not of transfer). With every learned VQF value at the core's, the
    learned VQF is its core on every trial of both (the pairing of the table is right, and the followed
    modulation changes nothing when nothing is learned)."""
    dirs = []
    for name in ("first", "second"):
        shutil.copytree(mini_index.root, tmp_path / name)
        dirs.append(tmp_path / name)
    cfg = load_config()
    for section, values in TINY_LEARNING_OFF.items():
        cfg[section].update(values)
    cfg["gains"]["vqf"] = {**cfg["gains"]["vqf"], **VQF_OFF}
    results = leave_one_dataset_out(dirs, tmp_path / "lodo", cfg, verbose=False)
    assert list(results) == ["first", "second"]
    for ds, per in results.items():
        assert set(ROWS) <= set(per)
        names = sorted(per["vqf_toggling"])
        assert names == sorted(mini_index.available)
        for n in names:
            learned, core = per["vqf_toggling"][n].errors["total"], per[CORE_OF["vqf_toggling"]][n].errors["total"]
            assert abs(learned - core) < 1e-6, (ds, n, learned, core)
        assert (tmp_path / "lodo" / f"without_{ds}" / "models" / "gains.json").is_file()
    text = lodo_table(results, dirs, "cmd")
    assert "## Left out: first (3 trials)" in text and "## Left out: second (3 trials)" in text
    first_all = next(ln for ln in text.splitlines() if ln.startswith("| all |"))
    assert "+0.0 % · 0/3/0" in first_all  # learned VQF vs core: three ties
    assert lodo_json(results)["first"]["vqf_core"][names[0]]["total"] == pytest.approx(
        results["first"]["vqf_core"][names[0]].errors["total"])


def test_left_out_datasets_and_the_pretrained_model_train_with_the_pretrained_search(monkeypatch, tmp_path):
    """``run.lodo`` (each dataset left out) and ``run.pretrained`` (every dataset) train with the same search, the
    pretrained recipe's (``run.config.pretrained_config``): the check is of the model that ships. The training
    is replaced by a stub that records its config and stops."""
    import togglecf.run.lodo as lodo_module
    import togglecf.run.pretrained as pretrained_module

    class Seen(Exception):
        pass

    def stub(cfg, **kwargs):
        raise Seen(cfg)
    for module in (lodo_module, pretrained_module):
        monkeypatch.setattr(module, "run_training", stub)
    with pytest.raises(Seen) as left_out:
        lodo_module._left_out(tmp_path / "a", [tmp_path / "b"], tmp_path / "m", None, False, {}, None)
    with pytest.raises(Seen) as pretrained:
        pretrained_module.train_pretrained_models([tmp_path / "a", tmp_path / "b"], tmp_path, verbose=False)
    for seen in (left_out, pretrained):
        search = VQFGainSearch.from_dict(seen.value.args[0]["gains"]["vqf"])
        assert search.tau_acc == (3.0,) and search.objective == "mean_dataset_log_ratio"
