"""A model trained at one rate means the same at another (issue 12): the motion-state classifier,
trained at BROAD's 285.7 Hz, predicts the same state on a real trial averaged down to 95.2 Hz
(``togglecf.run.transfer.decimate_trial``, ``pipelines/decimate.py``), because windows, hops and the feature filters are in seconds; and
decimation itself keeps the layout the loader reads."""
import importlib
import sys
from pathlib import Path

import numpy as np
import pytest

from conftest import train_tiny_models
from togglecf.data import DatasetIndex
from togglecf.learn.compiled import CompiledModels
from togglecf.run.transfer import decimate_trial
from togglecf.toggling import load_compiled_models

PIPELINES = Path(__file__).resolve().parents[1] / "pipelines"


@pytest.fixture(scope="module")
def decimate():
    sys.path.insert(0, str(PIPELINES))
    try:
        return importlib.import_module("decimate")
    finally:
        sys.path.remove(str(PIPELINES))


def _states(models, gyr, acc, mag, fs):
    p = models.predict_samples(gyr, acc, mag, fs)[:, :len(models.class_names)]
    return np.where(np.isfinite(p[:, 0]), np.argmax(np.nan_to_num(p), axis=1), -1)


@pytest.mark.broad
def test_classifier_predicts_the_same_state_at_a_third_of_the_rate(broad_index, mini_index, mini_kind, tmp_path):
    """Tiny models trained at 285.7 Hz on the mini trials; trial 05 (not among them) at its rate and
    every 3 samples averaged: the held state agrees on >= 90 % of the decimated samples (the
    issue's bar; 92.9 % with these tiny models, deterministic for the seed; the misses sit at
    state changes, where the two rates' windows end 1-2 native samples apart)."""
    if mini_kind != "broad":  # TOGGLECF_MINI=synthetic with BROAD present
        pytest.skip("the 90 % bar was measured with tiny models trained on the real mini cuts, not on synthetic "
                    "trials (other trees, another classifier: no claim about how they transfer to trial 05)")
    m = load_compiled_models(train_tiny_models(mini_index.root, "02,07,24", tmp_path / "m"))
    # the classifier itself, without the out-of-range fallback (ranges of 3 short trials would refuse many
    # windows of trial 05 at both rates; this test is about what the trees predict)
    models = CompiledModels(m.forest, m.class_names, m.feature_settings, m.schema_hash)
    t = broad_index.load("05_undisturbed_slow_rotation_with_breaks_B")
    d = decimate_trial(t, 3)
    native = _states(models, t.gyr, t.acc, t.mag, t.fs)
    low = _states(models, d["imu_gyr"], d["imu_acc"], d["imu_mag"], t.fs / 3)
    at = np.arange(len(low)) * 3 + 2  # the native sample at the end of each averaged block
    both = (native[at] >= 0) & (low >= 0)
    assert both.mean() > 0.95  # every window after the first full one has a prediction
    agree = float(np.mean(native[at][both] == low[both]))
    assert agree >= 0.90, agree


def test_decimated_directory_loads_at_the_lower_rate(mini_index, mini_names, decimate, tmp_path):
    out = tmp_path / "dec"
    assert decimate.main([str(mini_index.root), str(out), "--factor", "3"]) == 0
    t0 = mini_index.load(mini_names[1])  # 07
    t = DatasetIndex.from_dir(out).load(mini_names[1])
    assert t.fs == pytest.approx(t0.fs / 3) and t.n_samples == t0.n_samples // 3
    np.testing.assert_allclose(t.gyr[5], t0.gyr[15:18].mean(axis=0))  # block average
    np.testing.assert_array_equal(t.opt_quat[5], t0.opt_quat[17])  # reference at the block's end
