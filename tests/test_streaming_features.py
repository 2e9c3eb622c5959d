"""The streaming (in-loop) features equal the vectorised definition in togglecf.features.windows."""
import numpy as np
import pytest

from togglecf.features.windows import FeatureSettings, compute_features
from togglecf.features.streaming import StreamingFeatures

# Same formulas, different summation order (direct sums here, shifted cumulative sums there):
# differences are rounding, ~1e-12 of the channel scale over a 50 000-sample trial.
RTOL, ATOL = 1e-8, 1e-8


@pytest.mark.broad
@pytest.mark.parametrize("settings", [
    FeatureSettings(), FeatureSettings(window_s=0.1, hop_s=0.02, ref_tau_s=2.0, lp_tau_s=0.1),
    # tight field gates and a short new-field time: every branch of the field reference is taken often
    FeatureSettings(ref_norm_th=0.005, ref_dip_th_deg=0.5, ref_new_s=0.2, ref_new_min_gyr_dps=5.0)])
def test_streaming_equals_vectorised_on_real_data(broad_trial, settings):
    n = 6000
    t = broad_trial.slice(20000, 20000 + n)  # a moving part of the trial
    X, ends = compute_features(t.gyr, t.acc, t.mag, t.fs, settings)
    sf = StreamingFeatures(t.fs, settings)
    rows, k = [], 0
    for i in range(n):
        sf.push(t.gyr[i], t.acc[i], t.mag[i])
        if k < len(ends) and i == ends[k]:
            assert sf.ready
            rows.append(sf.features())
            k += 1
    np.testing.assert_allclose(np.array(rows), X, rtol=RTOL, atol=ATOL)


def test_not_ready_before_a_full_window():
    sf = StreamingFeatures(100.0, FeatureSettings(window_s=0.1))
    for _ in range(9):
        sf.push(np.zeros(3), np.array([0, 0, 9.81]), np.array([0, 20.0, -40]))
    assert not sf.ready
    sf.push(np.zeros(3), np.array([0, 0, 9.81]), np.array([0, 20.0, -40]))
    assert sf.ready


def test_bad_sample_does_not_poison_references():
    sf = StreamingFeatures(100.0, FeatureSettings(window_s=0.1))
    good = (np.zeros(3), np.array([0, 0, 9.81]), np.array([0, 20.0, -40]))
    for _ in range(20):
        sf.push(*good)
    sf.push(np.full(3, np.nan), np.full(3, np.nan), np.full(3, np.inf))
    for _ in range(11):  # the bad sample and the jerk that uses it have left the ring
        sf.push(*good)
    f = sf.features()
    assert np.all(np.isfinite(f))


@pytest.mark.broad
def test_bad_first_and_middle_samples_streaming_equals_vectorised(broad_trial):
    """A NaN first sample (a sensor still starting) and NaN/inf samples later: both
    implementations start the EMA references at the first finite sample, hold them over bad
    ones, and give the same features (NaN where a bad sample is in the window)."""
    settings = FeatureSettings()
    n = 3000
    t = broad_trial.slice(20000, 20000 + n)
    gyr, acc, mag = t.gyr.copy(), t.acc.copy(), t.mag.copy()
    acc[0] = np.nan
    mag[:3] = np.nan
    acc[1500], mag[2200], gyr[2500] = np.inf, np.nan, np.nan
    X, ends = compute_features(gyr, acc, mag, t.fs, settings)
    sf = StreamingFeatures(t.fs, settings)
    rows, k = [], 0
    for i in range(n):
        sf.push(gyr[i], acc[i], mag[i])
        if k < len(ends) and i == ends[k]:
            rows.append(sf.features())
            k += 1
    rows = np.array(rows)
    np.testing.assert_array_equal(np.isnan(rows), np.isnan(X))
    np.testing.assert_allclose(rows, X, rtol=RTOL, atol=ATOL)
    late = ends > 2600  # one window after the last bad sample: every feature is finite again
    assert np.isfinite(X[late]).all()
    # the references did start: mag_norm_dev is small, not |m| (reference stuck at NaN or 0)
    from togglecf.features.windows import feature_schema

    j = feature_schema(settings).names.index("mag_norm_dev_last")
    assert np.nanmax(np.abs(X[late, j])) < 5.0


def _window_features_reference(ring, last):
    """The window's features as plain Python: one column at a time, sums in ring order (Python floats are
    IEEE doubles, so a sequential sum here is the same operation as the kernel's)."""
    L, cols = ring.shape
    out = []
    for c in range(cols - 1):
        col = [float(v) for v in ring[:, c]]
        s = 0.0
        for v in col:
            s += v
        mean = s / L
        if not np.isfinite(mean):
            out += [np.nan] * 4
            continue
        q = 0.0
        for v in col:
            q += (v - mean) * (v - mean)
        lo = hi = col[0]
        for v in col:
            lo, hi = (v if v < lo else lo), (v if v > hi else hi)
        out += [mean, float(np.sqrt(q / L)), lo, hi]
    e = 0.0
    for v in ring[:, -1]:
        e += float(v)
    return np.array(out + [e / L if np.isfinite(e) else np.nan] + list(last))


def test_window_features_bit_for_bit_as_a_plain_reference():
    """The kernel sums each column in ring order, so its row equals a plain sequential reference exactly (not
    within a tolerance), NaN and inf columns included; a faster rewrite of the kernel must keep that."""
    from togglecf.features.streaming import AUX_LAST, N_FEATURES, N_LAST, N_RING, window_features
    rng = np.random.default_rng(7)
    for trial in range(20):
        L = int(rng.integers(1, 90))
        ring = rng.normal(size=(L, N_RING)) * rng.lognormal(0.0, 3.0, size=N_RING)
        if trial % 3 == 0:  # a missing sample in some columns, an infinite one in another
            ring[rng.integers(L), rng.integers(N_RING, size=2)] = np.nan
            ring[rng.integers(L), rng.integers(N_RING)] = np.inf
        aux = np.zeros(AUX_LAST + N_LAST + 3)
        aux[AUX_LAST:AUX_LAST + N_LAST] = rng.normal(size=N_LAST)
        out = np.empty(N_FEATURES)
        window_features(ring, aux, out)
        np.testing.assert_array_equal(out, _window_features_reference(ring, aux[AUX_LAST:AUX_LAST + N_LAST]))
