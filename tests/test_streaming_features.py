"""The streaming (in-loop) features equal the vectorised definition in togglecf.features."""
import numpy as np
import pytest

from togglecf.features import FeatureSettings, compute_features
from togglecf.streaming_features import StreamingFeatures

# Same formulas, different summation order (direct sums here, shifted cumulative sums there):
# differences are rounding, ~1e-12 of the channel scale over a 50 000-sample trial.
RTOL, ATOL = 1e-8, 1e-8


@pytest.mark.broad
@pytest.mark.parametrize("settings", [FeatureSettings(), FeatureSettings(window_s=0.1, hop_s=0.02, ref_tau_s=2.0,
                                                                         lp_tau_s=0.1)])
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
    for _ in range(10):  # one window later the bad sample has left the ring
        sf.push(*good)
    f = sf.features()
    assert np.all(np.isfinite(f))
