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


@njit(cache=True)
def window_features(ring, aux, out):
    """Feature row of the window ending at the last pushed sample (needs ``L`` samples).

    Channels outer, samples inner: each channel's sum, extremes and squared deviations are summed in
    ring order in local variables (kept in registers; accumulators in arrays would be stored and
    reloaded at every sample, as numba cannot prove they do not alias the ring), the same values bit
    for bit as a loop over the rows."""
    L = ring.shape[0]
    nw = ring.shape[1] - 1
    for c in range(nw):
        s = 0.0
        lo = ring[0, c]
        hi = ring[0, c]
        for i in range(L):
            v = ring[i, c]
            s += v
            if v < lo:
                lo = v
            if v > hi:
                hi = v
        mean = s / L  # non-finite with a non-finite value in the window: then unused
        if not math.isfinite(mean):  # (finite iff the sum is) a non-finite value in the window:
            # the channel's stats are missing
            for j in range(4):
                out[4 * c + j] = math.nan
            continue
        ss = 0.0
        for i in range(L):
            d = ring[i, c] - mean
            ss += d * d
        out[4 * c] = mean
        out[4 * c + 1] = math.sqrt(ss / L)
        out[4 * c + 2] = lo
        out[4 * c + 3] = hi
    e = 0.0
    for i in range(L):
        e += ring[i, nw]
    out[4 * nw] = e / L if math.isfinite(e) else math.nan
    for j in range(N_LAST):
        out[4 * nw + 1 + j] = aux[AUX_LAST + j]


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
