"""The out-of-range fallback (``learn.ranges``; issue 12): feature training ranges in the model
metadata, the counting rule (vectorised == compiled loop), a window out of range gives no
prediction (so the learned VQF filter *is* its core there), the fallback diagnostic, the refusal of
models trained without ranges, and training on trials at different rates."""
import json
import shutil

import numpy as np
import pytest

from togglecf.features.windows import FEATURE_VERSION, FeatureSchema, SchemaMismatchError
from togglecf.filters import VQFCoreFilter
from togglecf.learn.compiled import CompiledModels
from togglecf.learn.dataset import common_rate
from togglecf.learn.models import load_bundle
from togglecf.learn.ranges import (
    DEFAULT_MAX_OUT_OF_RANGE,
    RANGE_QUANTILES,
    feature_ranges,
    range_arrays,
    window_out_of_range,
    windows_out_of_range,
)
from togglecf.run.config import load_config
from togglecf.run.train import run_training
from togglecf.run.transfer import write_decimated
from togglecf.toggling.inloop import ModelTogglingFilter, ModelVQFTogglingFilter


def test_feature_ranges_are_quantiles_of_finite_values():
    rng = np.random.default_rng(0)
    X = rng.standard_normal((2000, 3))
    X[::7, 1] = np.nan  # missing values do not count
    X[:, 2] = np.nan  # a feature never seen: unbounded
    r = feature_ranges(X, ["a", "b", "c"])
    assert r["quantiles"] == list(RANGE_QUANTILES) and r["max_out_of_range"] == DEFAULT_MAX_OUT_OF_RANGE
    assert r["low"][0] == pytest.approx(np.quantile(X[:, 0], RANGE_QUANTILES[0]), abs=0)
    col = X[:, 1][np.isfinite(X[:, 1])]
    assert r["high"][1] == pytest.approx(np.quantile(col, RANGE_QUANTILES[1]), abs=0)
    assert r["low"][2] is None and r["high"][2] is None
    json.dumps(r)  # stored in metadata.json: plain JSON, no NaN
    low, high, frac = range_arrays(r, ["a", "b", "c"])
    assert np.isnan(low[2]) and np.isnan(high[2]) and frac == DEFAULT_MAX_OUT_OF_RANGE
    with pytest.raises(ValueError, match="names differ"):
        range_arrays(r, ["a", "c", "b"])
    with pytest.raises(ValueError, match="fraction"):
        feature_ranges(X, ["a", "b", "c"], max_out_of_range=1.5)


def test_counting_rule_and_its_threshold():
    low = np.array([0.0, 0.0, 0.0, 0.0, np.nan])  # the last feature is unbounded: never counted
    high = np.array([1.0, 1.0, 1.0, 1.0, np.nan])
    inside = np.array([0.5, 0.5, 0.5, 0.5, 99.0])
    one_out = np.array([2.0, 0.5, 0.5, 0.5, 99.0])  # 1 of 4 bounded features out: 0.25
    nan_out = np.array([np.nan, 0.5, 0.5, 0.5, 99.0])  # a missing value is not "out"
    assert not window_out_of_range(inside, low, high, 0.0)
    assert window_out_of_range(one_out, low, high, 0.2)  # 0.25 > 0.2
    assert not window_out_of_range(one_out, low, high, 0.25)  # "more than": 0.25 is not more than 0.25
    assert not window_out_of_range(nan_out, low, high, 0.0)
    rows = np.vstack([inside, one_out, nan_out])
    assert windows_out_of_range(rows, low, high, 0.2).tolist() == [False, True, False]
    assert not windows_out_of_range(rows, low, high, 1.0).any()  # 1 disables the fallback


@pytest.fixture(scope="module")
def tiny_bundle(tiny_model_dir):
    return load_bundle(tiny_model_dir)


def test_trained_models_store_their_ranges(tiny_bundle):
    meta = tiny_bundle.metadata
    assert meta["bundle_format"] == 3
    r = meta["feature_ranges"]
    assert r["names"] == list(tiny_bundle.schema.names)
    finite = [(lo, hi) for lo, hi in zip(r["low"], r["high"]) if lo is not None]
    assert len(finite) > 0.9 * len(r["names"]) and all(lo <= hi for lo, hi in finite)


def _models_with_ranges(bundle, low, high, frac):
    m = CompiledModels.from_bundle(bundle)
    return CompiledModels(m.forest, m.class_names, m.feature_settings, m.schema_hash, low, high, frac)


def test_out_of_range_windows_give_no_prediction_and_the_vqf_filter_is_its_core(tiny_bundle, mini_trial):
    t = mini_trial
    n_f = CompiledModels.from_bundle(tiny_bundle).forest.n_features
    # an empty range [1, 0]: every finite feature value is out of it
    never = _models_with_ranges(tiny_bundle, np.ones(n_f), np.zeros(n_f), 0.2)
    out = ModelVQFTogglingFilter(t.fs, models=never, tau_acc_states=(1.0, 3.0, 5.0, 10.0)).update_batch(
        t.gyr, t.acc, t.mag)
    first = np.flatnonzero(~np.isnan(out.diagnostics["fallback"]) & (out.diagnostics["fallback"] == 1.0))
    assert first.size and out.diagnostics["fallback"][first[0]:].min() == 1.0  # every window from the first on
    assert out.diagnostics["fallback"][:first[0]].max() == 0.0  # before the first window: no window, no fallback
    assert np.isnan(out.diagnostics["p_rest"]).all()
    core = VQFCoreFilter(t.fs).update_batch(t.gyr, t.acc, t.mag)
    assert np.array_equal(out.quat, core.quat)  # no prediction -> the core's own coefficients, untouched
    # the vectorised predictions for gain learning follow the same rule
    pred = never.predict_samples(t.gyr, t.acc, t.mag, t.fs)
    assert np.isnan(pred).all()


def test_out_of_range_windows_make_the_toggling_cf_model_free(tiny_bundle, mini_trial):
    """Every window out of range: the toggling CF with models in the loop gives exactly the output of
    the same filter with every state at the slowest learned time constant per sensor and the learned
    terms off (no bias estimate, no noise removal): the models play no part."""
    t = mini_trial
    n_f = CompiledModels.from_bundle(tiny_bundle).forest.n_features
    never = _models_with_ranges(tiny_bundle, np.ones(n_f), np.zeros(n_f), 0.2)
    learned = dict(tau_acc=(0.1732, 1.748, 6.998, 70.0), tau_mag=(0.6982, 3.498, 11.66, 35.0), bias_tau=1.748)
    out = ModelTogglingFilter(t.fs, models=never, **learned).update_batch(t.gyr, t.acc, t.mag)
    assert np.nanmax(out.diagnostics["fallback"]) == 1.0
    off = ModelTogglingFilter(t.fs, models=never, tau_acc=(70.0,) * 4, tau_mag=(35.0,) * 4, bias_tau=-1.0,
                              noise_weight_acc=0.0, noise_weight_mag=0.0).update_batch(t.gyr, t.acc, t.mag)
    assert np.array_equal(out.quat, off.quat)
    trusted = ModelTogglingFilter(t.fs, models=CompiledModels.from_bundle(tiny_bundle), **learned).update_batch(
        t.gyr, t.acc, t.mag)
    assert np.abs(trusted.quat - out.quat).max() > 1e-3  # in range, the learned gains do act


def test_in_range_models_predict_and_the_two_rules_agree(tiny_bundle, mini_trial):
    """With the models' own training ranges the loop's fallback flags equal the vectorised rule's
    NaN rows sample by sample (same windows, same comparisons), on a trial the models trained on
    (so most windows are in range) and on the same trial with the gyro in °/s instead of rad/s (a
    unit mix-up: 57x the rates, unlike anything trained on)."""
    t = mini_trial
    models = CompiledModels.from_bundle(tiny_bundle)
    gains = dict(tau_acc=(0.1732, 1.748, 6.998, 17.5), tau_mag=(0.6982, 3.498, 11.66, 35.0))
    for scale in (1.0, np.degrees(1.0)):
        gyr = scale * t.gyr
        out = ModelTogglingFilter(t.fs, models=models, **gains).update_batch(gyr, t.acc, t.mag)
        pred = models.predict_samples(gyr, t.acc, t.mag, t.fs)
        fb = out.diagnostics["fallback"] == 1.0
        first_window = np.flatnonzero(~np.isnan(out.diagnostics["p_rest"]) | fb)[0]
        after_first = np.arange(t.n_samples) >= first_window
        assert np.array_equal(fb, np.isnan(pred[:, 0]) & after_first)
        if scale == 1.0:
            assert fb.mean() < 0.05  # its own training data: (almost) always trusted
        else:
            assert fb.mean() > 0.5  # the moving windows (~10 of the 14 s) at 57x their rates: refused


def test_full_state_holds_the_fallback_flag(tiny_bundle, mini_trial):
    t = mini_trial.slice(0, 2000)
    n_f = CompiledModels.from_bundle(tiny_bundle).forest.n_features
    never = _models_with_ranges(tiny_bundle, np.ones(n_f), np.zeros(n_f), 0.2)
    full = ModelVQFTogglingFilter(t.fs, models=never).update_batch(t.gyr, t.acc, t.mag)
    f = ModelVQFTogglingFilter(t.fs, models=never)
    f.update_batch(t.gyr[:1000], t.acc[:1000], t.mag[:1000])
    saved = f.get_state()
    g = ModelVQFTogglingFilter(t.fs, models=never)
    g.set_state(saved)
    rest = g.update_batch(t.gyr[1000:], t.acc[1000:], t.mag[1000:])
    assert np.array_equal(rest.quat, full.quat[1000:])
    assert np.array_equal(rest.diagnostics["fallback"], full.diagnostics["fallback"][1000:])


def test_models_without_ranges_are_refused_with_retrain(tiny_model_dir, tmp_path):
    old = tmp_path / "old"
    shutil.copytree(tiny_model_dir, old)
    meta = json.loads((old / "metadata.json").read_text())
    del meta["feature_ranges"]
    meta["bundle_format"] = 2
    (old / "metadata.json").write_text(json.dumps(meta))
    with pytest.raises(ValueError, match=r"without feature ranges .*retrain it with `togglecf train`"):
        CompiledModels.from_bundle(load_bundle(old))


def test_models_of_an_older_feature_version_are_refused_with_retrain(tiny_model_dir, tmp_path):
    """Feature version 1 had raw magnetometer channels: its trees index other columns, so no
    setting can feed them; the message says to retrain (and names the directory)."""
    old = tmp_path / "v1"
    shutil.copytree(tiny_model_dir, old)
    meta = json.loads((old / "metadata.json").read_text())
    schema = dict(meta["feature_schema"], version=FEATURE_VERSION - 1)
    schema["hash"] = FeatureSchema.from_dict({k: v for k, v in schema.items() if k != "hash"}).hash
    meta["feature_schema"] = schema
    (old / "metadata.json").write_text(json.dumps(meta))
    with pytest.raises(SchemaMismatchError, match=rf"{old}: trained on feature schema v{FEATURE_VERSION - 1}, "
                                                  rf"this togglecf computes v{FEATURE_VERSION}.*retrain it"):
        CompiledModels.from_bundle(load_bundle(old))


# ------------------------------------------------------------------------------ several rates

def test_common_rate():
    assert common_rate([100.0, 100.0 * (1 + 1e-9)]) == 100.0
    assert common_rate([285.714, 95.238]) is None


def test_training_on_trials_at_two_rates(mini_index, tmp_path):
    names = sorted(mini_index.available)
    slow = write_decimated(mini_index, tmp_path / "slow", 3)
    cfg = load_config({"run": {"data": [str(mini_index.root), str(slow)]},
                       "classifier": {"n_estimators": 4, "max_depth": 3},
                       "regressor": {"n_estimators": 2, "max_depth": 3}, "gains": {"learn": False}})
    res = run_training(cfg, out=tmp_path / "m", cv=False, verbose=False)
    meta = res["metadata"]
    fs = mini_index.load(names[0]).fs
    assert meta["sampling_rate"] is None and meta["window"]["window_samples"] is None
    assert meta["sampling_rates"] == sorted({round(fs, 6), round(fs / 3, 6)})
    assert {p["fs"] for p in meta["per_trial"].values()} == {fs, fs / 3}
    # the models run at either rate (windows and hops are in seconds)
    models = CompiledModels.from_bundle(load_bundle(tmp_path / "m"))
    t = mini_index.load(names[0])
    for rate, step in ((fs, 1), (fs / 3, 3)):
        out = ModelTogglingFilter(rate, models=models, tau_acc=(1.0,) * 4, tau_mag=(10.0,) * 4).update_batch(
            t.gyr[::step], t.acc[::step], t.mag[::step])
        assert np.isfinite(out.quat).all()
