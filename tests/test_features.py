"""Feature extraction: causality, equality with a slow per-window loop, schema checks."""
import math

import numpy as np
import pytest

from togglecf.data.broad import GRAVITY
from togglecf.features.windows import (LAST_CHANNELS, WINDOW_CHANNELS, FeatureSettings, SchemaMismatchError,
                                       compute_features, feature_schema, hop_length, window_end_indices,
                                       window_length)
from togglecf.simulate import imu_from_orientation, mag_disturbance_intervals, random_smooth_trajectory

FS = 100.0


def _signals(rng, n=2000):
    gyr = rng.standard_normal((n, 3))
    acc = rng.standard_normal((n, 3)) + [0.0, 0.0, GRAVITY]
    mag = 3 * rng.standard_normal((n, 3)) + [0.0, 20.0, -40.0]
    return gyr, acc, mag


def _slow_features(gyr, acc, mag, fs, s: FeatureSettings, ends):
    """Straight per-sample recursion + per-window loop, the definitions of the module docstring."""
    n = gyr.shape[0]
    L = window_length(fs, s.window_s)
    lam_r = math.exp(-1.0 / (s.ref_tau_s * fs))
    lam_p = math.exp(-1.0 / (s.lp_tau_s * fs))
    n_new = max(1, round(s.ref_new_s * fs))
    th_dip, w_new = math.radians(s.ref_dip_th_deg), math.radians(s.ref_new_min_gyr_dps)
    ch = {k: np.zeros(n) for k in set(WINDOW_CHANNELS) | set(LAST_CHANNELS) | {"gyr_energy"}}
    r = d = p = None
    for k in range(n):
        a, m, w = acc[k], mag[k], gyr[k]
        an, mn = math.sqrt(a @ a), math.sqrt(m @ m)
        dip = math.asin(max(-1.0, min(1.0, -(a @ m) / (an * mn))))
        if k == 0:
            r, d, p = mn, dip, a.copy()
            cr, cd, cn = mn, dip, 0
        for i, ax in enumerate("xyz"):
            ch[f"gyr_{ax}"][k], ch[f"acc_{ax}"][k] = w[i], a[i]
            ch[f"acc_hp_{ax}"][k] = a[i] - p[i]
        ch["gyr_norm"][k] = math.sqrt(w @ w)
        ch["gyr_energy"][k] = w @ w
        ch["acc_norm_dev"][k] = an - GRAVITY
        ch["jerk"][k] = 0.0 if k == 0 else math.sqrt(np.sum((a - acc[k - 1]) ** 2)) * fs
        ch["mag_norm_dev"][k] = mn - r
        ch["dip_dev"][k] = dip - d
        # the references seen by sample k+1: follow the field where it agrees (r, d and the candidate)
        agree = abs(mn - r) < s.ref_norm_th * r and abs(dip - d) < th_dip
        if agree:
            r, d = lam_r * r + (1 - lam_r) * mn, lam_r * d + (1 - lam_r) * dip
        if abs(mn - cr) < s.ref_norm_th * cr and abs(dip - cd) < th_dip:
            cn = min(n_new, cn + (math.sqrt(w @ w) >= w_new))
            cr, cd = lam_r * cr + (1 - lam_r) * mn, lam_r * cd + (1 - lam_r) * dip
            if not agree and cn >= n_new:
                r, d = cr, cd
        else:
            cr, cd, cn = mn, dip, 0
        p = lam_p * p + (1 - lam_p) * a
    rows = []
    for k in ends:
        row = []
        for c in WINDOW_CHANNELS:
            x = ch[c][k - L + 1:k + 1]
            row += [x.mean(), x.std(), x.min(), x.max()]
        row.append(ch["gyr_energy"][k - L + 1:k + 1].mean())
        row += [ch[c][k] for c in LAST_CHANNELS]
        rows.append(row)
    return np.array(rows)


def test_window_end_indices():
    # window 0.2 s at 100 Hz = 20 samples, hop 0.05 s = 5 samples: first full window ends at 19
    ends = window_end_indices(100, FS, 0.05, 0.2)
    assert ends[0] == 19 and np.all(np.diff(ends) == 5) and ends[-1] <= 99
    assert np.array_equal(window_end_indices(20, FS, 0.05), [4, 9, 14, 19])
    assert window_length(FS, 0.2) == 20 and hop_length(FS, 0.05) == 5


def test_vectorised_equals_slow_loop(rng):
    gyr, acc, mag = _signals(rng, 600)
    s = FeatureSettings(window_s=0.17, hop_s=0.03, ref_tau_s=0.5, lp_tau_s=0.2)  # odd window, short taus
    X, ends = compute_features(gyr, acc, mag, FS, s)
    ref = _slow_features(gyr, acc, mag, FS, s, ends)
    assert X.shape == ref.shape == (len(ends), len(feature_schema(s).names))
    # cumulative sums vs direct sums and lfilter vs the Python recursion differ by rounding only
    np.testing.assert_allclose(X, ref, rtol=1e-9, atol=1e-9)


def test_vectorised_equals_slow_loop_with_new_fields(rng):
    """The same with a new-field time of 5 samples: the candidate often becomes the reference."""
    gyr, acc, mag = _signals(rng, 600)
    s = FeatureSettings(ref_tau_s=0.5, ref_new_s=0.05)
    X, ends = compute_features(gyr, acc, mag, FS, s)
    np.testing.assert_allclose(X, _slow_features(gyr, acc, mag, FS, s, ends), rtol=1e-9, atol=1e-9)


def test_every_sample_hop(rng):
    gyr, acc, mag = _signals(rng, 300)
    s = FeatureSettings(window_s=0.1, hop_s=0.001)  # hop rounds to 1 sample
    X, ends = compute_features(gyr, acc, mag, FS, s)
    assert np.array_equal(ends, np.arange(9, 300))
    np.testing.assert_allclose(X, _slow_features(gyr, acc, mag, FS, s, ends), rtol=1e-9, atol=1e-9)


@pytest.mark.parametrize("window_s, hop_s", [(0.05, 0.08), (0.2, 0.05), (0.23, 0.07), (0.3, 0.01)])
def test_min_max_paths_agree(rng, window_s, hop_s):
    """Block min/max (hop longer or shorter than the window, with and without remainder, and the
    van Herk fallback for many tiny blocks) equal the per-window loop. Min/max themselves are
    exact; the 1e-12 tolerance only covers the per-sample channels (numpy norms vs math.sqrt),
    while a wrong window would be off by O(1)."""
    gyr, acc, mag = _signals(rng, 700)
    s = FeatureSettings(window_s=window_s, hop_s=hop_s)
    X, ends = compute_features(gyr, acc, mag, FS, s)
    ref = _slow_features(gyr, acc, mag, FS, s, ends)
    names = feature_schema(s).names
    minmax = [i for i, n in enumerate(names) if n.endswith(("_min", "_max"))]
    np.testing.assert_allclose(X[:, minmax], ref[:, minmax], rtol=1e-12, atol=1e-12)
    irregular = np.sort(rng.choice(np.arange(window_length(FS, window_s) - 1, 700), 50, replace=False))
    Xi, _ = compute_features(gyr, acc, mag, FS, s, ends=irregular)
    np.testing.assert_allclose(Xi, _slow_features(gyr, acc, mag, FS, s, irregular), rtol=1e-9, atol=1e-9)


def test_causal(rng):
    """Changing samples after k never changes the features of windows ending at or before k."""
    gyr, acc, mag = _signals(rng, 2000)
    s = FeatureSettings()
    X, ends = compute_features(gyr, acc, mag, FS, s)
    for k in (300, 1234, 1999):
        g2, a2, m2 = gyr.copy(), acc.copy(), mag.copy()
        g2[k + 1:] *= -3.0
        a2[k + 1:] += 50.0
        m2[k + 1:] = rng.standard_normal(m2[k + 1:].shape) * 100
        X2, ends2 = compute_features(g2, a2, m2, FS, s)
        past = ends <= k
        np.testing.assert_array_equal(X2[past], X[past])  # exactly: only earlier samples enter
        if (~past).any():
            assert not np.allclose(X2[~past], X[~past])


def test_schema_hash_and_check():
    a = feature_schema(FeatureSettings())
    b = feature_schema(FeatureSettings(window_s=0.3))
    assert a.hash == feature_schema(FeatureSettings()).hash and a.hash != b.hash
    a.check(feature_schema(FeatureSettings()))
    with pytest.raises(SchemaMismatchError, match="window_s=0.3 vs 0.2"):
        a.check(b)
    reordered = type(a)(a.version, a.names[::-1], a.settings)
    with pytest.raises(SchemaMismatchError, match="order differs"):
        a.check(reordered)
    with pytest.raises(ValueError, match="window_s"):
        FeatureSettings(window_s=0.0)


def _field_enu(norm_ut, dip_deg):
    """The earth's field in ENU at a site: ``norm_ut`` [µT], pointing ``dip_deg`` below north."""
    d = math.radians(dip_deg)
    return np.array([0.0, norm_ut * math.cos(d), -norm_ut * math.sin(d)])


def test_features_do_not_see_the_site_of_an_undisturbed_field():
    """The same motion at two sites (60 µT / dip 70° and 25 µT / dip 20°: farther apart than
    BROAD's lab and the phone data) gives the same features: the
    magnetometer enters only relative to its running reference (feature version 2 on). The
    tolerance is rounding: the undisturbed |m| and dip are constant, so their deviations are
    differences of nearly equal numbers (~1e-14 µT, ~1e-15 rad)."""
    fs = 100.0
    q = random_smooth_trajectory(fs, 6.0, seed=3)
    feats = []
    for norm, dip in ((60.0, 70.0), (25.0, 20.0)):
        t = imu_from_orientation(q, fs, mag_earth=_field_enu(norm, dip))
        feats.append(compute_features(t.gyr, t.acc, t.mag, fs)[0])
    np.testing.assert_allclose(feats[0], feats[1], rtol=0, atol=1e-9)
    # and a disturbance does show: 10 µT along east for 1 s moves mag_norm_dev
    t = imu_from_orientation(q, fs, mag_earth=_field_enu(25.0, 20.0),
                             mag_disturbance_earth=mag_disturbance_intervals(len(q), fs, ((3.0, 4.0, (10.0, 0.0, 0.0)),)))
    X, ends = compute_features(t.gyr, t.acc, t.mag, fs)
    col = feature_schema().names.index("mag_norm_dev_last")
    inside = (ends >= 3.1 * fs) & (ends < 4.0 * fs)
    assert np.all(np.abs(X[inside, col]) > 1.0) and np.all(np.abs(feats[1][~inside & (ends < 3 * fs), col]) < 1e-9)


def _turning_in_a_field(fs, seconds, rate_dps, scale_from_to=None):
    """A level sensor turning about the vertical at ``rate_dps`` in a 50 µT field with dip 60°;
    ``scale_from_to = (t0, t1, c)`` multiplies the field by ``c`` from t0 to t1 [s] (a disturbance
    of the norm only, dip unchanged). Returns gyr, acc, mag, t."""
    n = int(round(seconds * fs))
    t = np.arange(n) / fs
    w = math.radians(rate_dps)
    gyr = np.zeros((n, 3))
    gyr[:, 2] = w
    acc = np.tile([0.0, 0.0, GRAVITY], (n, 1))
    h, v = 50.0 * math.cos(math.radians(60.0)), -50.0 * math.sin(math.radians(60.0))
    mag = np.stack([h * np.sin(w * t), h * np.cos(w * t), np.full(n, v)], axis=1)  # north seen from the turning body
    if scale_from_to is not None:
        t0, t1, c = scale_from_to
        mag[(t >= t0) & (t < t1)] *= c
    return gyr, acc, mag, t


def _mag_norm_dev_last(gyr, acc, mag, fs, s=None):
    X, ends = compute_features(gyr, acc, mag, fs, s)
    return X[:, feature_schema(s).names.index("mag_norm_dev_last")], ends / fs


def test_reference_holds_through_a_sustained_disturbance():
    """A still sensor in a field 20 % stronger for 60 s (10 µT): the reference does not follow
    (version 2's 10-s EMA had followed it within some 30 s), so mag_norm_dev shows the 10 µT
    for the whole disturbance and 0 before and after. Tolerance: rounding (the norm is constant)."""
    fs = 100.0
    dev, t = _mag_norm_dev_last(*_turning_in_a_field(fs, 120.0, 0.0, (30.0, 90.0, 1.2))[:3], fs)
    np.testing.assert_allclose(dev[(t >= 30.0) & (t < 90.0)], 10.0, atol=1e-9)
    np.testing.assert_allclose(dev[(t < 30.0) | (t >= 90.0)], 0.0, atol=1e-9)


@pytest.mark.parametrize("fs", [100.0, 285.714])
def test_a_new_field_becomes_the_reference_after_ref_new_s_of_turning(fs):
    """Turning at 30 °/s (above ref_new_min_gyr_dps), a field that stays 20 % stronger agrees with
    itself from its first sample, so after ref_new_s = 20 s it is the reference (the deviation
    drops to 0) and the old field, when it returns at 60 s, is a disturbance for 20 s in turn.
    The switch times are the same in seconds at both rates, to the sample (1/fs)."""
    s = FeatureSettings()
    dev, t = _mag_norm_dev_last(*_turning_in_a_field(fs, 100.0, 30.0, (20.0, 60.0, 1.2))[:3], fs, s)
    tol = 1.0 / fs + FeatureSettings().hop_s  # one sample, plus the hop of the window ends
    for t_on, level in ((20.0, 10.0), (60.0, -10.0)):
        shown = (t >= t_on) & (np.abs(dev - level) < 1e-6)
        assert t[shown].min() < t_on + tol and abs(t[shown].max() - (t_on + s.ref_new_s)) < tol
    np.testing.assert_allclose(dev[(t >= 40.0 + tol) & (t < 60.0)], 0.0, atol=1e-9)
    np.testing.assert_allclose(dev[t >= 80.0 + tol], 0.0, atol=1e-9)


def test_a_still_sensor_never_takes_a_new_field():
    """Not turning, the same 20 % stronger field is never accepted: a disturbance that rotates
    with the sensor (a magnet on it) would look like a steady new field while the sensor is still."""
    fs = 100.0
    dev, t = _mag_norm_dev_last(*_turning_in_a_field(fs, 100.0, 0.0, (10.0, 100.0, 1.2))[:3], fs)
    np.testing.assert_allclose(dev[t >= 10.0], 10.0, atol=1e-9)


def test_bad_and_zero_norm_samples_leave_the_reference():
    """NaN and zero-norm magnetometer samples in an undisturbed stretch: afterwards the features
    are those of the run without them (the reference neither moved nor restarted)."""
    fs = 100.0
    gyr, acc, mag, t = _turning_in_a_field(fs, 30.0, 30.0)
    mag = mag * (1.0 + 0.02 * np.sin(0.7 * t))[:, None]  # a slowly varying norm, so the reference moves
    bad = mag.copy()
    bad[1000:1005] = np.nan
    bad[1500:1505] = 0.0
    clean, ends = compute_features(gyr, acc, mag, fs)
    dirty, _ = compute_features(gyr, acc, bad, fs)
    later = ends > 1505 + window_length(fs, FeatureSettings().window_s)
    # the reference moves by (1 − λ)·(|m| − r) per sample, (1 − λ) = 1e-3 and |m| − r ≤ 2 µT here: skipping
    # 10 samples changes it by < 0.02 µT; a restart at the first good sample would move it by ~|m| − r ~ 1 µT
    np.testing.assert_allclose(dirty[later], clean[later], atol=0.02)
    assert np.all(np.isfinite(dirty[later]))
