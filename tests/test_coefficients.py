"""The coefficient records of the filter kernels (``filters.base``, "Coefficients"): every filter's
``params`` is its ``Coefficients`` NamedTuple, ``use_mag`` and ``max_dt`` first, its fields
carry the settings they name, and no kernel reads coefficients by position."""
import ast
import math
import pickle
from pathlib import Path
from typing import get_type_hints

import numpy as np
import pytest

import togglecf
from togglecf.features.streaming import FeatureCoefficients, StreamingFeatures
from togglecf.features.windows import FeatureSettings, window_length
from togglecf.filters import FILTERS
from togglecf.filters.acc_mag import AccMagFilter
from togglecf.filters.aqua import AquaFilter
from togglecf.filters.base import COMMON_COEFFICIENTS, OrientationFilter, make_coefficients
from togglecf.filters.complementary import CFCoefficients, ComplementaryFilter
from togglecf.filters.ekf import EKFFilter
from togglecf.filters.gyro_only import GyroOnlyFilter
from togglecf.filters.madgwick import MadgwickFilter
from togglecf.filters.mahony import MahonyFilter
from togglecf.filters.timeconst import gain
from togglecf.filters.toggling import TogglingFilter

FS = 285.714
CLASSES = {**FILTERS, "toggling": TogglingFilter}
PKG = Path(togglecf.__file__).resolve().parent
KERNEL_FILES = sorted((PKG / "filters").glob("*.py")) + [PKG / "features" / "streaming.py"]


def _positional_params_reads(path):
    """``params[...]`` (or ``x[...]`` after ``x = params`` in the same function) in any function of
    the module; docstrings and comments do not count."""
    hits = []
    for fn in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if not isinstance(fn, ast.FunctionDef):
            continue
        names = {"params"}
        for node in ast.walk(fn):  # aliases: x = params
            if (isinstance(node, ast.Assign) and isinstance(node.value, ast.Name) and node.value.id in names):
                names.update(t.id for t in node.targets if isinstance(t, ast.Name))
        hits += [f"{path.name}:{node.lineno}" for node in ast.walk(fn)
                 if isinstance(node, ast.Subscript) and isinstance(node.value, ast.Name) and node.value.id in names]
    return sorted(set(hits))


def test_the_scan_finds_positional_reads(tmp_path):
    p = tmp_path / "k.py"
    p.write_text('"""params[0] in a docstring is fine"""\ndef step(state, params):\n    # params[1]\n'
                 '    a = params.alpha\n    p = params\n    return a + params[2] + p[3]\n'
                 'def qmul(p, q):\n    return p[0] * q[0]\n')
    assert _positional_params_reads(p) == ["k.py:6"]


@pytest.mark.parametrize("path", KERNEL_FILES, ids=lambda p: p.name)
def test_no_kernel_reads_params_by_position(path):
    assert _positional_params_reads(path) == []


@pytest.mark.parametrize("use_mag", [True, False], ids=["9D", "6D"])
@pytest.mark.parametrize("name", sorted(CLASSES))
def test_params_is_the_filters_coefficients_record(name, use_mag):
    cls = CLASSES[name]
    f = cls(FS, use_mag=use_mag, max_dt=0.05)
    rec = cls.Coefficients
    assert rec is not OrientationFilter.Coefficients, f"{name} declares no Coefficients of its own"
    assert type(f.params) is rec
    assert rec._fields[:2] == COMMON_COEFFICIENTS == ("use_mag", "max_dt")
    assert f.params.use_mag == (1.0 if use_mag else 0.0)
    assert f.params.max_dt == 0.05
    assert set(f._coefficients()) == set(rec._fields[2:])
    _check_declared_types(rec, f.params)


def _check_declared_types(rec, params):
    """Every value has its field's declared type (nested records checked likewise), so one compiled
    kernel per filter."""
    hints = get_type_hints(rec)
    for field, value in zip(rec._fields, params):
        kind = hints[field]
        if isinstance(kind, type) and issubclass(kind, tuple) and hasattr(kind, "_fields"):  # a nested record
            assert type(value) is kind, (field, value)
            _check_declared_types(kind, value)
            continue
        assert kind in (float, int, np.ndarray), field
        if kind is np.ndarray:
            assert isinstance(value, np.ndarray) and value.dtype == np.float64 and value.flags.c_contiguous
        else:
            assert type(value) is kind, (field, value)


def test_values_are_converted_to_the_declared_types():
    f = ComplementaryFilter(FS, tau=0, max_dt=1)  # ints from a config file (τ = 0: α = 1)
    assert f.params == (1.0, 1.0, 1.0) and all(type(v) is float for v in f.params)
    out = f.update_batch(np.zeros((3, 3)), np.tile([0.0, 0.0, 9.8], (3, 1)), np.tile([0.0, 20.0, -40.0], (3, 1)))
    assert np.all(np.isfinite(out.quat))
    with pytest.raises(TypeError, match="missing"):
        make_coefficients(CFCoefficients, use_mag=1.0, max_dt=0.1)
    with pytest.raises(TypeError, match="unknown"):
        make_coefficients(CFCoefficients, use_mag=1.0, max_dt=0.1, alpha=0.1, beta=0.2)


def test_a_record_without_the_common_fields_is_refused():
    from typing import NamedTuple

    class Bad(NamedTuple):
        alpha: float
        use_mag: float
        max_dt: float

    with pytest.raises(TypeError, match="use_mag"):
        type("BadFilter", (OrientationFilter,), {"Coefficients": Bad})


def test_cf_tau_gives_the_per_sample_alpha():
    for tau in (-1.0, 0.0, 0.01, 12.5, 1000.0):
        assert ComplementaryFilter(FS, tau=tau).params.alpha == gain(tau, 1.0 / FS)
    assert (ComplementaryFilter(FS, tau=-1.0).params.alpha, ComplementaryFilter(FS, tau=0.0).params.alpha) == (0.0, 1.0)
    assert ComplementaryFilter(FS).params.alpha == pytest.approx(0.00028, rel=1e-3)  # the former default


def test_cf_alpha_drives_the_blend():
    """α = 0 is gyro integration, α = 1 (9D) the acc/mag orientation: the kernel reads ``alpha``."""
    rng = np.random.default_rng(3)
    g = 0.3 * rng.standard_normal((400, 3))
    a = np.array([0.3, -0.2, 9.8]) + 0.5 * rng.standard_normal((400, 3))
    m = np.array([2.0, 20.0, -40.0]) + rng.standard_normal((400, 3))
    for use_mag in (True, False):
        mm = m if use_mag else None
        np.testing.assert_allclose(ComplementaryFilter(FS, tau=-1.0, use_mag=use_mag).update_batch(g, a, mm).quat,
                                   GyroOnlyFilter(FS, use_mag=use_mag).update_batch(g, a, mm).quat, atol=1e-12)
    # (in 6D the CF's α = 1 keeps the gyro's heading, the acc/mag filter holds the first one)
    np.testing.assert_allclose(ComplementaryFilter(FS, tau=0.0).update_batch(g, a, m).quat,
                               AccMagFilter(FS).update_batch(g, a, m).quat, atol=1e-12)


def test_madgwick_and_mahony_gains():
    p = MadgwickFilter(FS, beta=0.123).params
    assert p.beta == 0.123 and p.mag_ref_scale == 1.0
    assert MadgwickFilter(FS, c_code_mag_step=True).params.mag_ref_scale == 0.5
    p = MahonyFilter(FS, Kp=0.9, Ki=0.004, use_mag=False).params
    assert (p.use_mag, p.Kp, p.Ki) == (0.0, 0.9, 0.004)


@pytest.mark.parametrize("cls", [AquaFilter, EKFFilter], ids=["aqua", "ekf"])
def test_fields_named_after_settings_carry_them(cls):
    f = cls(FS)
    per_sample = {"gain_acc": "tau_acc", "gain_mag": "tau_mag", "bias_alpha": "bias_tau"} if cls is AquaFilter else {}
    for field, tau_name in per_sample.items():  # AQUA's gains: per sample from the time constants
        assert getattr(f.params, field) == gain(getattr(f.settings, tau_name), 1.0 / FS), field
    for field in cls.Coefficients._fields[2:]:
        if field in per_sample:
            continue
        v = getattr(f.settings, field)
        assert getattr(f.params, field) == (float(v) if isinstance(v, bool) else v), field
    if cls is AquaFilter:
        p = AquaFilter(FS, adaptive=False, estimate_bias=False).params
        assert (p.adaptive, p.estimate_bias) == (0.0, 0.0)


def test_toggling_coefficients():
    ta, tm = (0.1732, 1.165, 8.748), (0.8731, 3.498, 17.5)
    f = TogglingFilter(FS, states=("static", "slow", "fast"), tau_acc=ta, tau_mag=tm, static_state="slow",
                       output_tau=0.002907, bias_tau=3.498, bias_gate=0.04, mag_disturbance_scale=5.0,
                       noise_weight_acc=0.6, noise_weight_mag=0.4, use_mag=False)
    p, ts = f.params, 1.0 / FS
    assert (p.use_mag, p.layout.n_states, p.layout.size, p.static_index) == (0.0, 3, 9, 1)
    assert np.array_equal(p.alpha_acc, [gain(t, ts) for t in ta]) and np.array_equal(p.alpha_mag, [gain(t, ts) for t in tm])
    assert (p.gamma, p.bias_gain) == (gain(0.002907, ts), gain(3.498, ts))
    # the former per-sample values at 285.714 Hz
    np.testing.assert_allclose([*p.alpha_acc, *p.alpha_mag, p.gamma, p.bias_gain],
                               [0.02, 0.003, 0.0004, 0.004, 0.001, 0.0002, 0.7, 0.001], rtol=1e-3)
    assert (p.bias_gate, p.mag_disturbance_scale, p.noise_weight_acc, p.noise_weight_mag) == (0.04, 5.0, 0.6, 0.4)


def test_toggling_one_hot_prediction_selects_that_states_gains():
    """With a one-hot prediction of state s the gains used are alpha_acc[s], alpha_mag[s]; a
    non-finite probability row falls back to the cautious gains: per sensor the smallest."""
    f = TogglingFilter(FS, states=("a", "b", "c"), static_state="a", tau_acc=(0.0098, 0.1732, 3.498),
                       tau_mag=(0.0157, 0.3482, 0.8731))
    n = 50
    g, acc, mag = np.zeros((n, 3)), np.tile([0.1, 0.0, 9.8], (n, 1)), np.tile([0.0, 20.0, -40.0], (n, 1))
    for s in range(3):
        pred = np.zeros((n, 9))
        pred[:, s] = 1.0
        d = TogglingFilter(FS, f.settings).update_batch(g, acc, mag, predictions=pred).diagnostics
        assert d["alpha_acc"][-1] == f.params.alpha_acc[s] and d["alpha_mag"][-1] == f.params.alpha_mag[s]
    pred = np.full((n, 9), np.nan)
    d = TogglingFilter(FS, f.settings).update_batch(g, acc, mag, predictions=pred).diagnostics
    assert d["alpha_acc"][-1] == min(f.params.alpha_acc) and d["alpha_mag"][-1] == min(f.params.alpha_mag)


def test_streaming_feature_coefficients():
    s = FeatureSettings()
    sf = StreamingFeatures(FS, s)
    p = sf.params
    assert type(p) is FeatureCoefficients
    assert p.fs == FS and p.window_length == window_length(FS, s.window_s) == sf.L
    assert p.ref_decay == math.exp(-1.0 / (s.ref_tau_s * FS)) and p.lp_decay == math.exp(-1.0 / (s.lp_tau_s * FS))
    assert p.gravity == float(sf.schema.settings["gravity"])


@pytest.mark.parametrize("name", sorted(CLASSES))
def test_filters_with_coefficient_records_pickle(name):
    """Process pools send filters to workers: the record must survive pickling."""
    f = CLASSES[name](FS)
    g = pickle.loads(pickle.dumps(f))
    assert type(g.params) is type(f.params)
    assert all(np.array_equal(a, b) if isinstance(a, np.ndarray) else a == b for a, b in zip(g.params, f.params))
