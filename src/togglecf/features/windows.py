"""Causal sliding-window features over gyro, accelerometer and magnetometer.

A window of ``L = max(2, round(window_s·fs))`` samples *ends at the sample it describes*:
the window for sample ``k`` is ``[k−L+1, k]``. Windows are evaluated every
``H = max(1, round(hop_s·fs))`` samples at ``window_end_indices`` (``k = L−1, L−1+H, ...``), so
the toggling filter predicts at exactly those samples from the window ending there.

Per-sample channels (sample ``k``; ``a, m, ω`` = acc, mag, gyr; ``g = 9.81``):

* ``gyr_x/y/z``, ``gyr_norm = |ω_k|``, ``gyr_energy = |ω_k|²``
* ``acc_x/y/z``, ``acc_norm_dev = |a_k| − g``
* ``jerk = |a_k − a_{k−1}| · fs`` (0 at ``k = 0``)
* ``mag_norm_dev = |m_k| − r_{k−1}`` and ``dip_dev = δ_k − d_{k−1}``, with the dip angle
  ``δ_k = asin(−(a_k·m_k)/(|a_k||m_k|))`` [rad] and a causal reference ``(r, d)`` of the field's
  norm and dip that follows only an undisturbed field (``mag_reference_step``; VQF's
  magnetic reference logic, Laidig & Seel 2023, eqs. M2-M3, in the sensor frame):

  - sample ``k`` *agrees* with the reference when ``||m_k| − r| < ref_norm_th·r`` and
    ``|δ_k − d| < ref_dip_th_deg``; then ``r ← r + (1−λ)(|m_k| − r)`` (likewise ``d``), with
    ``λ = exp(−1/(ref_tau_s·fs))``; a disagreeing sample leaves the reference where it is, so a
    sustained disturbance stays visible in ``mag_norm_dev``/``dip_dev`` for as long as it lasts;
  - a *candidate* ``(c_r, c_d)`` follows the field in the same way while the field agrees with it
    and restarts at ``(|m_k|, δ_k)`` when it does not; it counts the agreeing samples taken while
    rotating (``|ω_k| ≥ ref_new_min_gyr_dps``); once it has ``round(ref_new_s·fs)`` of them, a
    sample that disagrees with the reference moves the reference to the candidate (a new
    undisturbed field, e.g. another room: a disturbance that rotates with the sensor changes
    norm or dip as it turns and never agrees that long);
  - the reference (and the candidate) start at the first usable sample, ``|m_k|`` finite and
    positive, before its deviations are taken (so they are 0: with a good first sample
    ``r_{−1} = |m_0|``, ``d_{−1} = δ_0``); the deviations before it are NaN, and an unusable
    sample later changes nothing.

  Why gated: a plain EMA as the reference would follow a sustained disturbance within some
  ``ref_tau_s`` of its start, and the deviation would be gone.
* ``acc_hp_x/y/z = a_k − p_{k−1}``, ``p`` the EMA of ``a`` with ``lp_tau_s`` (``p_{−1} = a_0``): the
  fast part of the specific force, a proxy for linear acceleration and vibration.

The magnetometer enters only relative to its own causal reference (``mag_norm_dev``, ``dip_dev``),
never as raw components or norm: the field's strength (25–65 µT) and dip angle depend on where
the sensor is, so a model that has seen them learns its training site's field and mistakes another
site's undisturbed field for a disturbance. A deviation from the reference means the same anywhere.

These definitions are ``FEATURE_VERSION``; models trained on features of another version are
refused (``learn.compiled``), as no setting recomputes them.

Non-finite input samples: a window that holds a non-finite value of a channel gives NaN
statistics of that channel (missing values for the trees); the references hold over bad
samples and start at the first finite one (the field reference: the first usable one, above).

Window statistics over ``[k−L+1, k]`` (``WINDOW_CHANNELS``): ``mean``, ``std`` (population,
``sqrt(max(0, E[(x−c)²] − E[x−c]²))`` with ``c`` the channel's value at sample 0, a shift that
only improves rounding), ``min``, ``max``; plus ``gyr_energy_mean``; plus the current value
(``_last``) of ``LAST_CHANNELS``. The vectorised code uses cumulative sums (mean, std) and
per-hop block minima/maxima (van Herk filters from ``scipy.ndimage`` for irregular ends); an
incremental implementation (ring buffer with running sums, ``streaming_features``) gives the
same values up to floating-point rounding (~1e-9 relative; min/max exactly).
"""
from __future__ import annotations

import hashlib
import json
import math
from dataclasses import asdict, dataclass
from typing import NamedTuple

import numpy as np
from numba import njit
from scipy.ndimage import maximum_filter1d, minimum_filter1d
from scipy.signal import lfilter

from togglecf.core.io import check_keys
from togglecf.data.broad import GRAVITY
from togglecf.filters.base import field_agrees

__all__ = ["FEATURE_VERSION", "FeatureSettings", "FeatureCoefficients", "FeatureSchema", "SchemaMismatchError",
           "feature_coefficients", "feature_schema", "mag_reference_start", "mag_reference_step",
           "window_end_indices", "window_length", "hop_length", "per_sample_channels", "compute_features",
           "trial_features", "WINDOW_CHANNELS", "LAST_CHANNELS"]

FEATURE_VERSION = 3
WINDOW_CHANNELS = ("gyr_x", "gyr_y", "gyr_z", "gyr_norm", "acc_x", "acc_y", "acc_z", "acc_norm_dev",
                   "jerk", "mag_norm_dev", "dip_dev")
STATS = ("mean", "std", "min", "max")
LAST_CHANNELS = ("gyr_norm", "acc_x", "acc_y", "acc_z", "acc_norm_dev", "mag_norm_dev", "dip_dev",
                 "acc_hp_x", "acc_hp_y", "acc_hp_z")
ALL_CHANNELS = tuple(dict.fromkeys(WINDOW_CHANNELS + LAST_CHANNELS + ("gyr_energy",)))


class SchemaMismatchError(ValueError):
    """A model was given features computed with a different schema than it was trained on."""


@dataclass(frozen=True)
class FeatureSettings:
    """Feature settings in physical units (module docstring).

    Attributes:
        window_s: window length [s].
        hop_s: spacing of the window ends [s].
        ref_tau_s: time constant [s] with which the field reference (and its candidate) follow an
            agreeing field.
        lp_tau_s: time constant [s] of the acc low-pass behind ``acc_hp``.
        ref_norm_th: largest deviation of |m| from the reference, relative to it, for a sample to
            agree with it (VQF's ``magNormTh``). Default 0.1.
        ref_dip_th_deg: largest deviation of the dip angle [°] (VQF's ``magDipTh``). Default 10.
        ref_new_s: rotating time [s] a new field must agree with itself before it becomes the
            reference (VQF's ``magNewTime``). Default 20.
        ref_new_min_gyr_dps: |ω| [°/s] from which a sample counts as rotating for ``ref_new_s``
            (VQF's ``magNewMinGyr``). Default 20.
    """

    window_s: float = 0.2
    hop_s: float = 0.05
    ref_tau_s: float = 10.0
    lp_tau_s: float = 0.5
    ref_norm_th: float = 0.1
    ref_dip_th_deg: float = 10.0
    ref_new_s: float = 20.0
    ref_new_min_gyr_dps: float = 20.0

    def __post_init__(self):
        for k, v in asdict(self).items():
            if not (isinstance(v, (int, float)) and np.isfinite(v) and v > 0):
                raise ValueError(f"FeatureSettings.{k} must be a positive number (units: see FeatureSettings), "
                                 f"got {v!r}")

    @classmethod
    def from_dict(cls, d: dict) -> "FeatureSettings":
        return cls(**{k: float(v) for k, v in check_keys(cls, d, "feature").items()})


class FeatureCoefficients(NamedTuple):
    """The per-sample constants of the features at one rate (``feature_coefficients``): what the
    numba kernels (``per_sample_channels``, ``streaming.push_sample``) and the C export read.

    Attributes:
        fs: sampling rate [Hz] (jerk = |Δa| · fs).
        window_length: L, samples per window (rows of the streaming ring buffer).
        ref_decay: λ_ref = exp(−1 / (ref_tau_s · fs)), the per-sample weight of the old value in
            the field reference and its candidate (the gain of an agreeing sample is 1 − λ_ref).
        lp_decay: λ_lp = exp(−1 / (lp_tau_s · fs)), the same for the acc low-pass behind acc_hp.
        gravity: g [m/s²] (acc_norm_dev = |a| − g).
        ref_norm_th: ``FeatureSettings.ref_norm_th`` (relative).
        ref_dip_th: ``ref_dip_th_deg`` in rad.
        ref_new_samples: round(ref_new_s · fs) (at least 1), the rotating samples after which a
            candidate becomes the reference.
        ref_new_min_gyr_sq: ``ref_new_min_gyr_dps`` in rad/s, squared [(rad/s)²].
    """

    fs: float
    window_length: int
    ref_decay: float
    lp_decay: float
    gravity: float
    ref_norm_th: float
    ref_dip_th: float
    ref_new_samples: int
    ref_new_min_gyr_sq: float


def feature_coefficients(fs: float, settings: FeatureSettings) -> FeatureCoefficients:
    """``FeatureSettings`` (physical units) to the per-sample constants at ``fs`` [Hz]."""
    return FeatureCoefficients(fs=float(fs), window_length=int(window_length(fs, settings.window_s)),
                               ref_decay=math.exp(-1.0 / (settings.ref_tau_s * fs)),
                               lp_decay=math.exp(-1.0 / (settings.lp_tau_s * fs)), gravity=float(GRAVITY),
                               ref_norm_th=float(settings.ref_norm_th),
                               ref_dip_th=math.radians(settings.ref_dip_th_deg),
                               ref_new_samples=max(1, int(round(settings.ref_new_s * fs))),
                               ref_new_min_gyr_sq=math.radians(settings.ref_new_min_gyr_dps) ** 2)


@dataclass(frozen=True)
class FeatureSchema:
    """The named, versioned feature list a model is trained on; ``hash`` covers names,
    version and settings."""

    version: int
    names: tuple
    settings: dict

    @property
    def hash(self) -> str:
        blob = json.dumps({"version": self.version, "names": list(self.names), "settings": self.settings},
                          sort_keys=True)
        return hashlib.sha256(blob.encode()).hexdigest()

    def to_dict(self) -> dict:
        return {"version": self.version, "names": list(self.names), "settings": dict(self.settings),
                "hash": self.hash}

    @classmethod
    def from_dict(cls, d: dict) -> "FeatureSchema":
        s = cls(int(d["version"]), tuple(d["names"]), dict(d["settings"]))
        if "hash" in d and d["hash"] != s.hash:
            raise SchemaMismatchError(f"feature schema hash {d['hash'][:12]} does not match its content "
                                      f"({s.hash[:12]}): the stored schema was edited")
        return s

    def check(self, other: "FeatureSchema", what: str = "model") -> None:
        """Raise ``SchemaMismatchError`` naming the first difference unless ``other`` is identical."""
        if other.hash == self.hash:
            return
        if other.version != self.version:
            why = f"version {other.version} given, {self.version} expected"
        elif tuple(other.names) != tuple(self.names):
            missing = [n for n in self.names if n not in other.names]
            extra = [n for n in other.names if n not in self.names]
            if missing or extra:
                why = f"missing features {missing[:5]}, unexpected features {extra[:5]}"
            else:
                i = next(i for i, (a, b) in enumerate(zip(self.names, other.names)) if a != b)
                why = f"feature order differs at column {i}: {other.names[i]!r} given, {self.names[i]!r} expected"
        else:
            diff = {k: (other.settings.get(k), v) for k, v in self.settings.items() if other.settings.get(k) != v}
            why = "settings differ (given, expected): " + ", ".join(f"{k}={a!r} vs {b!r}" for k, (a, b) in diff.items())
        raise SchemaMismatchError(
            f"{what} was trained on feature schema v{self.version} {self.hash[:12]} but got schema "
            f"v{other.version} {other.hash[:12]}: {why}. Recompute the features with the model's schema "
            f"(togglecf.features.windows.FeatureSettings(**schema.settings)) or retrain the model.")


def feature_names() -> tuple:
    names = [f"{c}_{s}" for c in WINDOW_CHANNELS for s in STATS]
    names.append("gyr_energy_mean")
    names += [f"{c}_last" for c in LAST_CHANNELS]
    return tuple(names)


def feature_schema(settings: FeatureSettings | None = None) -> FeatureSchema:
    s = settings or FeatureSettings()
    return FeatureSchema(FEATURE_VERSION, feature_names(), {**asdict(s), "gravity": GRAVITY})


def window_length(fs: float, window_s: float) -> int:
    return max(2, int(round(window_s * fs)))


def hop_length(fs: float, hop_s: float) -> int:
    return max(1, int(round(hop_s * fs)))


def window_end_indices(n: int, fs: float, hop: float, window: float | None = None) -> np.ndarray:
    """Samples at which a prediction is made: every ``hop_length(fs, hop)`` samples starting
    at the first sample with a full window (``window_length(fs, window) − 1``; sample
    ``hop_length − 1`` when ``window`` is None)."""
    h = hop_length(fs, hop)
    start = window_length(fs, window) - 1 if window is not None else h - 1
    return np.arange(start, n, h, dtype=np.int64)


def _ema_lagged(x: np.ndarray, lam: float) -> np.ndarray:
    """``r_{k−1}`` of the EMA ``r_k = λ r_{k−1} + (1−λ) x_k`` with ``r_{−1} = x_0`` (axis 0).

    Rows of ``x`` (N, C) with a non-finite value leave ``r`` unchanged, and ``r`` starts at the
    first finite row (as ``streaming_features.push_sample``; NaN before it)."""
    if np.isfinite(x).all():
        r = lfilter([1.0 - lam], [1.0, -lam], x, axis=0, zi=lam * x[:1])[0]
        out = np.empty_like(r)
        out[0] = x[0]
        out[1:] = r[:-1]
        return out
    out = np.empty_like(x)
    _ema_lagged_holding(np.ascontiguousarray(x, np.float64), lam, out)
    return out


@njit(cache=True)
def _ema_lagged_holding(x, lam, out):
    """The same recursion and rounding as ``lfilter`` (``(1−λ) x + λ r``), holding over bad rows."""
    n, c = x.shape
    r = x[0].copy()  # NaN when row 0 is bad: then the first finite row starts it
    for k in range(n):
        out[k] = r
        ok = True
        for j in range(c):
            if not np.isfinite(x[k, j]):
                ok = False
        if ok:
            started = True
            for j in range(c):
                if not np.isfinite(r[j]):
                    started = False
            for j in range(c):
                r[j] = (1.0 - lam) * x[k, j] + lam * r[j] if started else x[k, j]


# inline: called once per sample from the filter loop (``streaming.push_sample``), as push_sample itself
@njit(cache=True, inline="always")
def mag_reference_start(r, d, cand_r, cand_d, cand_n, mn, dip):
    """Before sample k's deviations: with no reference yet (``r`` NaN or 0; a reference is
    otherwise a positive norm) and a usable sample (|m_k| = ``mn`` finite and > 0), reference and
    candidate start at it."""
    if math.isfinite(mn) and mn > 0.0 and not r > 0.0:
        return mn, dip, mn, dip, 0.0
    return r, d, cand_r, cand_d, cand_n


@njit(cache=True, inline="always")
def _field_agrees(ref_r, ref_d, mn, dip, params):
    """|m_k| within ``ref_norm_th`` (relative) and δ_k within ``ref_dip_th`` of a field (VQF's M2/M3 test)."""
    return field_agrees(ref_r, ref_d, mn, dip, params.ref_norm_th, params.ref_dip_th)


@njit(cache=True, inline="always")
def mag_reference_step(r, d, cand_r, cand_d, cand_n, mn, dip, gyr_sq, params):
    """The field reference after sample k (module docstring): ``(r, d, cand_r, cand_d, cand_n)``
    [µT, rad, µT, rad, samples] updated with |m_k| = ``mn`` [µT], δ_k = ``dip`` [rad] (finite by
    construction) and |ω_k|² = ``gyr_sq`` [(rad/s)²]; ``params`` a ``FeatureCoefficients``. After
    ``mag_reference_start`` of the same sample. The same float64 operations in the vectorised and
    streaming features; ``tcf_features.c`` ports it to float32."""
    if not (math.isfinite(mn) and mn > 0.0):
        return r, d, cand_r, cand_d, cand_n  # a bad or zero-norm sample says nothing about the field
    k = 1.0 - params.ref_decay
    agree = _field_agrees(r, d, mn, dip, params)  # (M2)
    if agree:
        r += k * (mn - r)
        d += k * (dip - d)
    if _field_agrees(cand_r, cand_d, mn, dip, params):  # (M3)
        if gyr_sq >= params.ref_new_min_gyr_sq and cand_n < params.ref_new_samples:
            cand_n += 1.0
        cand_r += k * (mn - cand_r)
        cand_d += k * (dip - cand_d)
        if not agree and cand_n >= params.ref_new_samples:  # a new field: the candidate becomes the reference
            r, d = cand_r, cand_d
    else:
        cand_r, cand_d, cand_n = mn, dip, 0.0
    return r, d, cand_r, cand_d, cand_n


@njit(cache=True)
def _mag_reference_lagged(mn, dip, gyr_sq, params):
    """``(r_{k−1}, d_{k−1})`` for every sample k, ``(N, 2)`` (NaN before the first usable sample)."""
    n = mn.shape[0]
    out = np.empty((n, 2))
    r, d, cand_r, cand_d, cand_n = math.nan, math.nan, math.nan, math.nan, 0.0
    for i in range(n):
        r, d, cand_r, cand_d, cand_n = mag_reference_start(r, d, cand_r, cand_d, cand_n, mn[i], dip[i])
        out[i, 0] = r
        out[i, 1] = d
        r, d, cand_r, cand_d, cand_n = mag_reference_step(r, d, cand_r, cand_d, cand_n, mn[i], dip[i], gyr_sq[i],
                                                          params)
    return out


def per_sample_channels(gyr, acc, mag, fs: float, settings: FeatureSettings) -> dict:
    """The per-sample channels of the module docstring, each ``(N,)`` float64."""
    gyr, acc, mag = (np.ascontiguousarray(x, dtype=np.float64) for x in (gyr, acc, mag))
    ch = {}
    for pre, x in (("gyr", gyr), ("acc", acc)):
        for i, ax in enumerate("xyz"):
            ch[f"{pre}_{ax}"] = x[:, i]
    gn2 = np.einsum("ij,ij->i", gyr, gyr)
    ch["gyr_energy"] = gn2
    ch["gyr_norm"] = np.sqrt(gn2)
    an = np.sqrt(np.einsum("ij,ij->i", acc, acc))
    mn = np.sqrt(np.einsum("ij,ij->i", mag, mag))
    ch["acc_norm_dev"] = an - GRAVITY
    jerk = np.zeros(acc.shape[0])
    d = np.diff(acc, axis=0)
    jerk[1:] = np.sqrt(np.einsum("ij,ij->i", d, d)) * fs
    ch["jerk"] = jerk
    with np.errstate(invalid="ignore", divide="ignore"):
        cosang = np.einsum("ij,ij->i", acc, mag) / (an * mn)
    dip = np.arcsin(np.clip(-np.nan_to_num(cosang), -1.0, 1.0))
    coef = feature_coefficients(fs, settings)
    ref = _mag_reference_lagged(mn, dip, gn2, coef)
    ch["mag_norm_dev"] = mn - ref[:, 0]
    ch["dip_dev"] = dip - ref[:, 1]
    hp = acc - _ema_lagged(acc, coef.lp_decay)
    for i, ax in enumerate("xyz"):
        ch[f"acc_hp_{ax}"] = hp[:, i]
    return ch


def compute_features(gyr, acc, mag, fs: float, settings: FeatureSettings | None = None, ends=None):
    """Feature matrix ``(len(ends), F)`` (columns ``feature_schema(settings).names``) and ``ends``.

    ``ends`` defaults to ``window_end_indices(N, fs, hop_s, window_s)``; every end must be
    ``≥ L−1`` (a full window).
    """
    s = settings or FeatureSettings()
    n = np.shape(gyr)[0]
    L = window_length(fs, s.window_s)
    ends = window_end_indices(n, fs, s.hop_s, s.window_s) if ends is None else np.asarray(ends, np.int64)
    if ends.size and (ends.min() < L - 1 or ends.max() >= n):
        raise ValueError(f"window ends must lie in [{L - 1}, {n - 1}] (window of {L} samples)")
    ch = per_sample_channels(gyr, acc, mag, fs, s)
    W = np.empty((len(WINDOW_CHANNELS), n))  # channels in rows: contiguous along time
    for i, c in enumerate(WINDOW_CHANNELS):
        W[i] = ch[c]
    hi, lo = ends + 1, ends + 1 - L
    bad = ~np.isfinite(W)
    has_bad = bad.any()
    if has_bad:  # a window with a non-finite value of a channel gives NaN stats of it (missing)
        nbad = np.zeros((W.shape[0], n + 1))
        np.cumsum(bad, axis=1, out=nbad[:, 1:])
        bad_window = (nbad[:, hi] - nbad[:, lo]) > 0
        W = np.where(bad, 0.0, W)
    W0 = W - W[:, :1]
    c1 = np.zeros((W.shape[0], n + 1))
    c2 = np.zeros((W.shape[0], n + 1))
    np.cumsum(W0, axis=1, out=c1[:, 1:])
    np.multiply(W0, W0, out=W0)
    np.cumsum(W0, axis=1, out=c2[:, 1:])
    mean0 = (c1[:, hi] - c1[:, lo]) / L
    var = np.maximum((c2[:, hi] - c2[:, lo]) / L - mean0 * mean0, 0.0)
    mean = mean0 + W[:, :1]
    std = np.sqrt(var)
    mn, mx = _window_min_max(W, ends, L)
    if has_bad:
        for a in (mean, std, mn, mx):
            a[bad_window] = np.nan
    stats = np.stack([mean, std, mn, mx], axis=2).transpose(1, 0, 2).reshape(len(ends), -1)  # channel-major
    ge_ch = ch["gyr_energy"]
    ge_bad = ~np.isfinite(ge_ch)
    ge = np.concatenate([[0.0], np.cumsum(np.where(ge_bad, 0.0, ge_ch))])
    ge_mean = ((ge[hi] - ge[lo]) / L)[:, None]
    if ge_bad.any():
        nb = np.concatenate([[0], np.cumsum(ge_bad)])
        ge_mean[(nb[hi] - nb[lo]) > 0] = np.nan
    last = np.stack([ch[c][ends] for c in LAST_CHANNELS], axis=1)
    X = np.concatenate([stats, ge_mean, last], axis=1)
    return X, ends


def _window_min_max(W: np.ndarray, ends: np.ndarray, L: int):
    """Min and max of ``W (C, N)`` over the windows ``[k−L+1, k]`` for ``k`` in ``ends``.

    Evenly spaced ends (step ``H``): split the samples into blocks of ``H`` ending at the window
    ends; a window is its last ``q = L // H`` whole blocks plus the last ``r = L − qH`` samples of
    the block before, so per-block reductions and ``q`` elementwise minima give exact results in
    O(N). Otherwise (or for many tiny blocks) van Herk filters over all samples (scipy.ndimage).
    """
    J = len(ends)
    if J == 0:
        return np.empty((W.shape[0], 0)), np.empty((W.shape[0], 0))
    H = int(ends[1] - ends[0]) if J > 1 else L
    q, r = divmod(L, H)
    if J > 1 and np.all(np.diff(ends) == H) and q <= 16:
        start = int(ends[0]) - (q + 1) * H + 1
        stop = int(ends[-1]) + 1
        if start < 0:  # samples before the first window are never used: pad with any value
            P = np.concatenate([np.repeat(W[:, :1], -start, axis=1), W[:, :stop]], axis=1)
        else:
            P = W[:, start:stop]
        blocks = P.reshape(W.shape[0], J + q, H)
        out = []
        for red, acc in ((np.min, np.minimum), (np.max, np.maximum)):
            b = red(blocks, axis=2)  # block i of the array is block i−q relative to the first end
            res = red(blocks[:, :J, H - r:], axis=2) if r else b[:, 1:1 + J].copy()
            for d in range(0 if r else 1, q):
                acc(res, b[:, 1 + d:1 + d + J], out=res)
            out.append(res)
        return out[0], out[1]
    centre = ends - L + 1 + L // 2  # a centred filter of size L at `centre` covers [k−L+1, k]
    return (minimum_filter1d(W, L, axis=1, mode="nearest")[:, centre],
            maximum_filter1d(W, L, axis=1, mode="nearest")[:, centre])


def trial_features(trial, settings: FeatureSettings | None = None, ends=None):
    """``compute_features`` on a ``Trial``."""
    return compute_features(trial.gyr, trial.acc, trial.mag, trial.fs, settings, ends)
