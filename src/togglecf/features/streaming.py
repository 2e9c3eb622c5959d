"""The features of ``togglecf.features.windows``, computed one sample at a time inside numba loops.

``features.compute_features`` is the definition (and the vectorised version used for
training); this module keeps a ring buffer of the per-sample channels of the last ``L``
samples plus the causal EMA references, and computes the same feature row for the window
ending at the current sample. Equal to the vectorised features up to floating-point
rounding (mean/std are summed directly here, from shifted cumulative sums there).

Layout: ``ring (L, N_RING)`` holds ``WINDOW_CHANNELS`` then ``gyr_energy`` per sample;
``aux`` holds ``[count, pos, r_mag, d_dip, p_acc(3), prev_acc(3), last channels(10), c_mag, c_dip,
n_cand]`` (the field reference, the acc low-pass, the candidate field of
``windows.mag_reference_step``); ``params`` is the named record ``FeatureCoefficients`` of
``windows.feature_coefficients``. Non-finite samples do not update the references (so one bad
sample cannot poison them for the rest of a run; when the first samples are bad, the
references start at the first finite one); their channels enter the ring as NaN, which the
trees treat as missing values.
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit

from togglecf.features.windows import (
    LAST_CHANNELS,
    WINDOW_CHANNELS,
    FeatureCoefficients,
    FeatureSettings,
    feature_coefficients,
    feature_schema,
    mag_reference_start,
    mag_reference_step,
)

__all__ = ["N_AUX", "N_RING", "FeatureCoefficients", "StreamingFeatures", "push_sample", "window_features"]

N_WINDOW = len(WINDOW_CHANNELS)
N_RING = N_WINDOW + 1
N_LAST = len(LAST_CHANNELS)
AUX_LAST = 10  # aux index of the first *_last value
AUX_CAND = AUX_LAST + N_LAST  # aux index of the candidate field (c_mag, c_dip, n_cand)
N_AUX = AUX_CAND + 3
N_FEATURES = 4 * N_WINDOW + 1 + N_LAST
# ring column of each window channel, and where each "last" channel comes from
_RING = {c: i for i, c in enumerate(WINDOW_CHANNELS)}
_ACC_HP = {"acc_hp_x": 0, "acc_hp_y": 1, "acc_hp_z": 2}
assert all(c in _RING or c in _ACC_HP for c in LAST_CHANNELS), "a LAST channel is neither windowed nor acc_hp"
_LAST_SRC = np.array([_RING[c] if c in _RING else -1 - _ACC_HP[c] for c in LAST_CHANNELS], np.int64)
assert WINDOW_CHANNELS == ("gyr_x", "gyr_y", "gyr_z", "gyr_norm", "acc_x", "acc_y", "acc_z", "acc_norm_dev",
                           "jerk", "mag_norm_dev", "dip_dev"), \
    "features.WINDOW_CHANNELS changed: update push_sample to match"


# inline: called once per sample from the filter loop (``toggling.inloop``), where a call of its own
# (arguments unpacked, each array reference-counted) would cost as much as the work
@njit(cache=True, inline="always")
def push_sample(ring, aux, params, last_src, gyr, acc, mag):
    """Append one sample's channels (definitions in ``togglecf.features.windows``)."""
    fs, L, lam_lp, g = params.fs, params.window_length, params.lp_decay, params.gravity
    # the sample is read once into locals: numba cannot prove that gyr/acc/mag do not alias ring or
    # aux, so each read after a store to them would load it again (bench_toggling's in-loop cost)
    gx, gy, gz = gyr[0], gyr[1], gyr[2]
    ax, ay, az = acc[0], acc[1], acc[2]
    mx, my, mz = mag[0], mag[1], mag[2]
    count = int(aux[0])
    pos = int(aux[1])
    gn2 = gx * gx + gy * gy + gz * gz
    an = math.sqrt(ax * ax + ay * ay + az * az)
    mn = math.sqrt(mx * mx + my * my + mz * mz)
    cosang = (ax * mx + ay * my + az * mz) / (an * mn) if an * mn > 0.0 else 0.0
    if not math.isfinite(cosang):
        cosang = 0.0  # nan_to_num, as the vectorised version
    dip = math.asin(min(1.0, max(-1.0, -cosang)))
    if count == 0:  # the low-pass starts at the first sample, p_{-1} = a_0; the field reference at the first
        aux[2], aux[3] = math.nan, math.nan  # usable one (below; NaN deviations before it)
        aux[4], aux[5], aux[6] = ax, ay, az
        aux[7], aux[8], aux[9] = ax, ay, az
        jerk = 0.0
    else:
        dx, dy, dz = ax - aux[7], ay - aux[8], az - aux[9]
        jerk = math.sqrt(dx * dx + dy * dy + dz * dz) * fs
    # the field reference starts at the first usable sample, before its deviations
    aux[2], aux[3], aux[AUX_CAND], aux[AUX_CAND + 1], aux[AUX_CAND + 2] = mag_reference_start(
        aux[2], aux[3], aux[AUX_CAND], aux[AUX_CAND + 1], aux[AUX_CAND + 2], mn, dip)
    # indexed in place (a row view costs a reference count per sample)
    ring[pos, 0], ring[pos, 1], ring[pos, 2] = gx, gy, gz
    ring[pos, 3] = math.sqrt(gn2)
    ring[pos, 4], ring[pos, 5], ring[pos, 6] = ax, ay, az
    ring[pos, 7] = an - g
    ring[pos, 8] = jerk
    ring[pos, 9] = mn - aux[2]  # uses r_{k-1}
    ring[pos, 10] = dip - aux[3]
    ring[pos, 11] = gn2
    hp0, hp1, hp2 = ax - aux[4], ay - aux[5], az - aux[6]
    for j in range(last_src.shape[0]):
        s = last_src[j]
        aux[AUX_LAST + j] = ring[pos, s] if s >= 0 else (hp0 if s == -1 else (hp1 if s == -2 else hp2))
    # update the field reference with sample k (only from usable samples)
    aux[2], aux[3], aux[AUX_CAND], aux[AUX_CAND + 1], aux[AUX_CAND + 2] = mag_reference_step(
        aux[2], aux[3], aux[AUX_CAND], aux[AUX_CAND + 1], aux[AUX_CAND + 2], mn, dip, gn2, params)
    if math.isfinite(an):
        if math.isfinite(aux[4]) and math.isfinite(aux[5]) and math.isfinite(aux[6]):
            aux[4] = lam_lp * aux[4] + (1.0 - lam_lp) * ax
            aux[5] = lam_lp * aux[5] + (1.0 - lam_lp) * ay
            aux[6] = lam_lp * aux[6] + (1.0 - lam_lp) * az
        else:
            aux[4], aux[5], aux[6] = ax, ay, az
    aux[7], aux[8], aux[9] = ax, ay, az  # jerk next to a bad sample is missing, as in features
    aux[0] = count + 1
    aux[1] = pos + 1 if pos + 1 < L else 0  # (pos + 1) mod L without a division


assert N_RING % 4 == 0, "window_features walks the ring's columns four at a time"


@njit(cache=True, inline="always")
def _four_columns(ring, c):
    """Sums, minima, maxima and sums of squared deviations from the mean of ring columns ``c`` to
    ``c + 3``, each summed in ring order (tuples of four). Four columns side by side: each sum is a chain
    of dependent additions, and four independent chains run in the time of one (the values are the
    same bit for bit as one column at a time)."""
    L = ring.shape[0]
    s0 = s1 = s2 = s3 = 0.0
    lo0 = hi0 = ring[0, c]
    lo1 = hi1 = ring[0, c + 1]
    lo2 = hi2 = ring[0, c + 2]
    lo3 = hi3 = ring[0, c + 3]
    for i in range(L):
        v0, v1, v2, v3 = ring[i, c], ring[i, c + 1], ring[i, c + 2], ring[i, c + 3]
        s0 += v0
        s1 += v1
        s2 += v2
        s3 += v3
        lo0, hi0 = v0 if v0 < lo0 else lo0, v0 if v0 > hi0 else hi0
        lo1, hi1 = v1 if v1 < lo1 else lo1, v1 if v1 > hi1 else hi1
        lo2, hi2 = v2 if v2 < lo2 else lo2, v2 if v2 > hi2 else hi2
        lo3, hi3 = v3 if v3 < lo3 else lo3, v3 if v3 > hi3 else hi3
    m0, m1, m2, m3 = s0 / L, s1 / L, s2 / L, s3 / L  # non-finite with a non-finite value: then unused
    q0 = q1 = q2 = q3 = 0.0
    for i in range(L):
        d0, d1, d2, d3 = ring[i, c] - m0, ring[i, c + 1] - m1, ring[i, c + 2] - m2, ring[i, c + 3] - m3
        q0 += d0 * d0
        q1 += d1 * d1
        q2 += d2 * d2
        q3 += d3 * d3
    return (s0, s1, s2, s3), (lo0, lo1, lo2, lo3), (hi0, hi1, hi2, hi3), (q0, q1, q2, q3)


@njit(cache=True, inline="always")
def _column_features(out, c, L, total, lo, hi, sq_dev):
    """Ring column ``c``'s features into ``out``: a window channel's mean, std, min, max (all missing
    when the window holds a non-finite value: the mean is finite iff the sum is), the energy column's
    mean."""
    nw = N_WINDOW
    mean = total / L
    if c == nw:
        out[4 * nw] = mean if math.isfinite(mean) else math.nan
    elif not math.isfinite(mean):
        for j in range(4):
            out[4 * c + j] = math.nan
    else:
        out[4 * c] = mean
        out[4 * c + 1] = math.sqrt(sq_dev / L)
        out[4 * c + 2] = lo
        out[4 * c + 3] = hi


@njit(cache=True)
def window_features(ring, aux, out):
    """Feature row of the window ending at the last pushed sample (needs ``L`` samples).

    Each column's sum, extremes and squared deviations are summed in ring order in local variables,
    four columns side by side (``_four_columns``), the same values bit for bit as a loop over the rows."""
    L = ring.shape[0]
    for c in range(0, N_RING, 4):
        s, lo, hi, q = _four_columns(ring, c)
        _column_features(out, c, L, s[0], lo[0], hi[0], q[0])
        _column_features(out, c + 1, L, s[1], lo[1], hi[1], q[1])
        _column_features(out, c + 2, L, s[2], lo[2], hi[2], q[2])
        _column_features(out, c + 3, L, s[3], lo[3], hi[3], q[3])
    for j in range(N_LAST):
        out[4 * N_WINDOW + 1 + j] = aux[AUX_LAST + j]


class StreamingFeatures:
    """Python handle on the streaming extractor (tests, and the filter's state layout)."""

    def __init__(self, fs: float, settings: FeatureSettings):
        self.settings = settings
        self.schema = feature_schema(settings)
        self.params = feature_coefficients(fs, settings)
        self.L = self.params.window_length
        self.last_src = _LAST_SRC.copy()
        self.ring = np.zeros((self.L, N_RING))
        self.aux = np.zeros(N_AUX)
        if len(self.schema.names) != N_FEATURES:
            raise AssertionError("feature schema and streaming layout disagree")

    def push(self, gyr, acc, mag):
        push_sample(self.ring, self.aux, self.params, self.last_src, np.asarray(gyr, float), np.asarray(acc, float),
                    np.asarray(mag, float))

    @property
    def ready(self) -> bool:
        return self.aux[0] >= self.L

    def features(self) -> np.ndarray:
        out = np.empty(N_FEATURES)
        window_features(self.ring, self.aux, out)
        return out
