"""Models: schema checks, leakage-free CV by trial, determinism (on the shipped mini BROAD cuts),
held-out skill on real trials (the full BROAD)."""
import json
import tomllib

import numpy as np
import pytest
from conftest import TINY_TRAIN_TOML

from togglecf.features.windows import FeatureSettings, SchemaMismatchError, feature_schema
from togglecf.learn.models import (MotionClassifier, NoiseRegressor, classification_metrics, load_bundle,
                             regression_metrics, save_bundle)
from togglecf.learn.folds import window_group_folds as make_folds
from togglecf.run.config import load_config
from togglecf.run.train import run_training

SMALL = {"classifier": {"n_estimators": 25, "max_depth": 4}, "regressor": {"n_estimators": 25, "max_depth": 4},
         "features": {"hop_s": 0.1}}


def _small_config(**run):
    cfg = load_config()
    for sec, vals in SMALL.items():
        cfg[sec].update(vals)
    cfg["run"].update(run)
    return cfg


def _fitted(rng, schema, n=400):
    X = rng.standard_normal((n, len(schema.names)))
    y = (X[:, 0] > 0).astype(int) + (X[:, 1] > 1).astype(int)
    clf = MotionClassifier(n_estimators=5, max_depth=2).fit(X, y, schema, ("a", "b", "c"))
    regs = {t: NoiseRegressor(target=t, n_estimators=5, max_depth=2).fit(X, X[:, :3] * 0.5, schema)
            for t in ("acc", "mag")}
    return X, clf, regs


# ------------------------------------------------------------------------------ no data needed

def test_schema_mismatch_refused(tmp_path, rng):
    schema = feature_schema(FeatureSettings())
    X, clf, regs = _fitted(rng, schema)
    save_bundle(tmp_path, clf, regs, {"note": "test"})
    other = feature_schema(FeatureSettings(window_s=0.5))
    with pytest.raises(SchemaMismatchError, match=r"trained on feature schema .* window_s=0.5 vs 0.2"):
        load_bundle(tmp_path, expected_schema=other)
    bundle = load_bundle(tmp_path, expected_schema=schema)  # the right schema loads
    np.testing.assert_array_equal(bundle.classifier.predict(X, schema), clf.predict(X, schema))
    np.testing.assert_array_equal(bundle.regressors["acc"].predict(X), regs["acc"].predict(X))
    with pytest.raises(SchemaMismatchError, match="window_s"):
        bundle.regressors["mag"].predict(X, other)
    with pytest.raises(SchemaMismatchError, match=rf"expects {len(schema.names)} feature columns"):
        bundle.classifier.predict(X[:, :-1])
    # a model file changed after saving is refused
    (tmp_path / "acc_y.ubj").write_bytes((tmp_path / "acc_y.ubj").read_bytes()[:-1] + b"\x00")
    with pytest.raises(ValueError, match="sha256"):
        load_bundle(tmp_path)


def test_regressors_have_zero_base_score(rng):
    schema = feature_schema(FeatureSettings())
    _, _, regs = _fitted(rng, schema)
    for b in regs["acc"].boosters_:
        cfg = json.loads(b.save_config())
        assert float(cfg["learner"]["learner_model_param"]["base_score"].strip("[]")) == 0.0


def test_folds_partition_trials():
    group = np.repeat(np.arange(7), [50, 10, 30, 70, 20, 40, 60])
    folds = make_folds(group, 7, 3)
    assert len(folds) == 3
    tested = np.concatenate([te for _, te in folds])
    assert sorted(tested) == list(range(7))  # every trial is tested exactly once
    for tr, te in folds:
        assert not set(tr) & set(te) and set(tr) | set(te) == set(range(7))


def test_metrics_against_hand_values():
    y = np.array([0, 0, 1, 1])
    proba = np.array([[0.9, 0.1], [0.4, 0.6], [0.3, 0.7], [0.2, 0.8]])
    m = classification_metrics(y, proba, 2)
    assert m["balanced_accuracy"] == pytest.approx(0.75)
    assert m["roc_auc"] == pytest.approx(1.0)
    assert m["confusion"] == [[1, 1], [0, 2]]
    r = regression_metrics(np.array([[1.0, 2, 3], [3, 4, 5]]), np.zeros((2, 3)))
    assert r["rmse"] == pytest.approx(np.sqrt(np.mean([1, 4, 9, 9, 16, 25])))
    assert r["r2"] == pytest.approx(1 - (1 + 4 + 9 + 9 + 16 + 25) / 6.0)


# ------------------------------------------------------------- real trials: the shipped mini cuts

@pytest.fixture(scope="module")
def mini_cv_run(mini_index, tmp_path_factory):
    """Small CV (leave-one-trial-out over the 3 mini trials) on real data, a few seconds."""
    cfg = _small_config(cv_folds=3)
    return run_training(cfg, data_dir=mini_index.root, trials="02,07,24",
                        out=tmp_path_factory.mktemp("mini_cv_model"), verbose=False)


def test_no_leakage_in_cv(mini_cv_run):
    data, folds = mini_cv_run["data"], mini_cv_run["cv"]["folds"]
    L = data.window_samples
    for f in folds:
        test_g = [data.trials.index(t) for t in f["test_trials"]]
        train_g = [data.trials.index(t) for t in f["train_trials"]]
        assert not set(test_g) & set(train_g)
        train_rows = np.flatnonzero(np.isin(data.group, train_g) & data.train_mask)
        assert len(train_rows) == f["n_train"]
        # every sample of every training window belongs to a training trial
        assert not np.isin(data.group[train_rows], test_g).any()
        assert np.all(data.end[train_rows] - L + 1 >= 0)
    assert len(folds) == 3 and sorted(t for f in folds for t in f["test_trials"]) == sorted(data.trials)


def test_same_seed_byte_identical(mini_index, tmp_path):
    cfg = _small_config(seed=3)
    outs = []
    for i in range(2):
        out = tmp_path / f"run{i}"
        run_training(cfg, data_dir=mini_index.root, trials="02,24", out=out, cv=False, verbose=False)
        outs.append(out)
    files = sorted(p.name for p in outs[0].glob("*.ubj"))
    assert len(files) == 7  # classifier + 3 acc + 3 mag
    for name in files:
        assert (outs[0] / name).read_bytes() == (outs[1] / name).read_bytes(), name
    m0, m1 = (json.loads((o / "metadata.json").read_text()) for o in outs)
    assert m0["model_files"] == m1["model_files"]
    assert m0["feature_schema"]["hash"] == m1["feature_schema"]["hash"]


# ------------------------------------------------------------------- real BROAD trials (full data)

@pytest.fixture(scope="module")
def cv_run(broad_index, tmp_path_factory):
    """Small CV (leave-one-trial-out over 4 varied trials) on real data, ~30 s on 2 cores."""
    cfg = _small_config(cv_folds=4)
    return run_training(cfg, data_dir=broad_index.root, trials="02,07,10,24",
                        out=tmp_path_factory.mktemp("cv_model"), verbose=False)


@pytest.mark.broad
@pytest.mark.slow
def test_held_out_skill(cv_run):
    overall = cv_run["cv"]["overall"]
    clf, maj = overall["classifier"], overall["majority"]
    # the majority class has balanced accuracy 1/n_classes present; the model must clearly beat it
    assert clf["balanced_accuracy"] > maj["balanced_accuracy"] + 0.15
    assert clf["f1_macro"] > maj["f1_macro"] + 0.15
    assert clf["roc_auc"] > 0.75
    for f in cv_run["cv"]["folds"]:
        assert f["classifier"]["balanced_accuracy"] > f["majority"]["balanced_accuracy"]
    # held-out acc noise: better than predicting zero noise (R² of zero is <= 0 by construction)
    assert overall["acc"]["r2"] > 0.0
    assert overall["acc"]["rmse"] < overall["acc_zero"]["rmse"]


@pytest.mark.parametrize("earlier", ["another run's modes", "a damaged file"])
def test_training_replaces_an_earlier_gains_file(mini_index, tmp_path, earlier):
    """Training into a directory that holds an earlier ``gains.json``: the new file has this run's modes
    only (a mode of the earlier run beside the new models would pass their schema check with settings
    learned for other models), and a damaged earlier file does not stop the run."""
    out = tmp_path / "models"
    out.mkdir()
    stale = {"format": 2, "feature_schema_hash": "x", "vqf_6d": {"filter": "vqf_toggling", "settings": {}}}
    (out / "gains.json").write_text(json.dumps(stale) if earlier == "another run's modes" else "{ not json")
    cfg = load_config(tomllib.loads(TINY_TRAIN_TOML))
    cfg["gains"]["modes"] = ["9d"]
    run_training(cfg, data_dir=mini_index.root, trials="02,07,24", out=out, cv=False, verbose=False)
    gains = json.loads((out / "gains.json").read_text())
    assert {k for k in gains if k in ("9d", "6d", "vqf_9d", "vqf_6d")} == {"9d"}
    assert gains["feature_schema_hash"] == json.loads((out / "metadata.json").read_text())["feature_schema"]["hash"]
