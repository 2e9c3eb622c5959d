"""The toggling CF with its models compiled into the loop equals the same filter driven by
xgboost's own predictions; update == update_batch; the full state (window included) splits."""
import numpy as np
import pytest

from togglecf.core import quaternion as quat
from togglecf.features.windows import compute_features
from togglecf.filters.toggling import TogglingFilter
from togglecf.learn.compiled import CompiledModels
from togglecf.toggling.inloop import ModelTogglingFilter, ModelVQFTogglingFilter
from togglecf.learn.models import load_bundle

#: time constants [s]: per sample (0.02, 0.002, 0.0005, 0.0002), (0.005, 0.001, 0.0003, 0.0001), γ 0.7 at 285.714 Hz
GAINS = dict(tau_acc=(0.1732, 1.748, 6.998, 17.5), tau_mag=(0.6982, 3.498, 11.66, 35.0), output_tau=0.002907)


@pytest.fixture(scope="module")
def bundle(tiny_model_dir):
    return load_bundle(tiny_model_dir)


@pytest.fixture(scope="module")
def segment(mini_trial):
    """A trial with every motion state: the 4000-sample mini cut of trial 24 (it was 12000 samples of
    trial 05 when these tests needed the full BROAD; the claims are equalities between two
    implementations, which need realistic inputs, not unseen ones; the slices below, 0:2500 split at
    1001 and 0:4000, still fit). Without BROAD: the synthetic trial 24 (same length, every state)."""
    return mini_trial


def xgboost_predictions(bundle, t):
    """Per-sample predictions from xgboost on the vectorised features, held from each window end."""
    X, ends = compute_features(t.gyr, t.acc, t.mag, t.fs, CompiledModels.from_bundle(bundle).feature_settings)
    p = np.hstack([bundle.classifier.predict_proba(X, bundle.schema), bundle.regressors["acc"].predict(X, bundle.schema),
                   bundle.regressors["mag"].predict(X, bundle.schema)])
    pred = np.full((t.n_samples, p.shape[1]), np.nan)
    idx = np.searchsorted(ends, np.arange(t.n_samples), side="right") - 1  # last window end <= sample
    pred[idx >= 0] = p[idx[idx >= 0]]
    return pred


def test_compiled_models_equal_xgboost_driven_filter(bundle, segment):
    t = segment
    models = CompiledModels.from_bundle(bundle)
    inloop = ModelTogglingFilter(t.fs, models=models, **GAINS).update_batch(t.gyr, t.acc, t.mag)
    ref_pred = xgboost_predictions(bundle, t)
    names = [f"p_{s}" for s in models.class_names] + [f"eta_{s}_{a}" for s in ("acc", "mag") for a in "xyz"]
    got = np.column_stack([inloop.diagnostics[n] for n in names])
    # float32 leaf sums in xgboost vs float64 here, features rounded differently: ~1e-6 at most
    np.testing.assert_allclose(got, ref_pred, atol=1e-5, equal_nan=True)
    driven = TogglingFilter(t.fs, states=models.class_names, static_state=models.class_names[0], **GAINS)
    ref = driven.update_batch(t.gyr, t.acc, t.mag, predictions=ref_pred)
    assert np.degrees(quat.angle_between(inloop.quat, ref.quat)).max() < 1e-4


def test_update_equals_batch_and_full_state_splits(bundle, segment):
    t = segment.slice(0, 2500)
    models = CompiledModels.from_bundle(bundle)
    full = ModelTogglingFilter(t.fs, models=models, **GAINS).update_batch(t.gyr, t.acc, t.mag).quat
    f = ModelTogglingFilter(t.fs, models=models, **GAINS)
    single = np.array([f.update(t.gyr[i], t.acc[i], t.mag[i]) for i in range(t.n_samples)])
    assert np.array_equal(single, full)
    f1 = ModelTogglingFilter(t.fs, models=models, **GAINS)
    a = f1.update_batch(t.gyr[:1001], t.acc[:1001], t.mag[:1001]).quat  # split inside a hop
    f2 = ModelTogglingFilter(t.fs, models=models, **GAINS)
    f2.set_state(f1.get_state())
    b = f2.update_batch(t.gyr[1001:], t.acc[1001:], t.mag[1001:]).quat
    assert np.array_equal(np.vstack([a, b]), full)


def test_states_must_match_model_classes(bundle):
    models = CompiledModels.from_bundle(bundle)
    with pytest.raises(ValueError, match="differ from the model's classes"):
        ModelTogglingFilter(285.7, models=models, states=("a", "b"), tau_acc=(0.1, 0.1), tau_mag=(0.1, 0.1),
                            static_state="a")


def test_trees_of_zero_weighted_outputs_are_skipped_without_changing_the_result(bundle, segment):
    t = segment.slice(0, 4000)
    models = CompiledModels.from_bundle(bundle)
    full = ModelTogglingFilter(t.fs, models=models, **GAINS, noise_weight_acc=0.0)
    assert len(full.forest.roots) < len(models.forest.roots)  # the acc regressors' trees are dropped
    ref = ModelTogglingFilter(t.fs, models=models, **GAINS, noise_weight_acc=0.0)
    ref.forest = models.forest  # walk every tree
    a = full.update_batch(t.gyr, t.acc, t.mag)
    b = ref.update_batch(t.gyr, t.acc, t.mag)
    assert np.array_equal(a.quat, b.quat)


@pytest.mark.parametrize("use_mag,w_mag,sigma_m,mag_trees_kept", [
    (True, 1.0, 0.0, True),    # step 3 subtracts w_m η̂_m
    (True, 0.0, 10.0, True),   # step 4 still scales α_m with |η̂_m| (dropping them changed results: a bug once)
    (True, 0.0, 0.0, False),   # η̂_m unused
    (False, 1.0, 10.0, False),  # 6D: no magnetometer update at all
])
def test_magnetometer_trees_are_walked_exactly_when_the_filter_uses_them(bundle, segment, use_mag, w_mag, sigma_m,
                                                                         mag_trees_kept):
    t = segment.slice(0, 4000)
    models = CompiledModels.from_bundle(bundle)
    kw = dict(GAINS, noise_weight_mag=w_mag, mag_disturbance_scale=sigma_m)
    f = ModelTogglingFilter(t.fs, models=models, use_mag=use_mag, **kw)
    groups = set(np.unique(f.forest.tree_group).tolist())
    assert (set(models.layout.outputs(models.layout.eta_mag)) <= groups) == mag_trees_kept
    ref = ModelTogglingFilter(t.fs, models=models, use_mag=use_mag, **kw)
    ref.forest = models.forest  # every tree walked: the result must not change
    mag = t.mag if use_mag else None
    assert np.array_equal(f.update_batch(t.gyr, t.acc, mag).quat, ref.update_batch(t.gyr, t.acc, mag).quat)


@pytest.mark.parametrize("per_state_tau", [False, True])
def test_learned_vqf_walks_the_class_trees_only_where_its_per_state_values_differ(bundle, segment, per_state_tau):
    """The learned VQF whose per-state values are all the core's (here with the heading back-off on, as the
    pretrained recipe's model) gets nothing from the class probabilities: its loop walks only the η̂_m trees
    (the class outputs keep their base margins, a constant prior) and its orientation is the one with every
    tree walked within rounding: the blend Σ w_s ln τ of equal values is ln τ up to an ulp, exp() of it one ulp
    off τ (the bound of test_pretrained's learning-off test, 1e-12). With τ_acc per state the class trees are
    walked."""
    t = segment.slice(0, 4000)
    models = CompiledModels.from_bundle(bundle)
    layout = models.layout
    kw = dict(mag_disturbance_scale=10.0)
    if per_state_tau:
        kw["tau_acc_states"] = tuple(np.geomspace(1.5, 6.0, len(models.class_names)))
    f = ModelVQFTogglingFilter(t.fs, models=models, **kw)
    groups = set(np.unique(f.forest.tree_group).tolist())
    assert (set(layout.outputs(layout.probabilities)) <= groups) == per_state_tau
    assert not set(layout.outputs(layout.probabilities)) & groups or per_state_tau
    assert set(layout.outputs(layout.eta_mag)) <= groups
    ref = ModelVQFTogglingFilter(t.fs, models=models, **kw)
    ref.forest = models.forest  # every tree walked
    a, b = f.update_batch(t.gyr, t.acc, t.mag), ref.update_batch(t.gyr, t.acc, t.mag)
    assert np.abs(a.quat - b.quat).max() <= (0.0 if per_state_tau else 1e-12)
    p = a.diagnostics["p_" + models.class_names[0]]
    held = p[np.isfinite(p)]
    assert held.size and (np.ptp(held) > 0) == per_state_tau  # the prior is constant, the classifier's is not
