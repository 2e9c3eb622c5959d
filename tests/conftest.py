"""Shared fixtures. Real-data tests are marked ``broad``: skipped with the reason when BROAD is
absent, except when ``TOGGLECF_REQUIRE_DATA=1`` (set by .ci/run), where absence is an error.

``mini_index``: 14-s cuts of three real BROAD trials in ``tests/data/broad_mini`` (made from BROAD on
first use, never committed; see ``tests/data/README.md``), for the tests of what the code does with
real recordings that make no claim about the full dataset (models, export, C filter)."""
import os
import sys
from pathlib import Path

import numpy as np
import pytest
from hypothesis import settings

# CI: the same examples every run (a failure is reproducible); locally hypothesis explores anew
settings.register_profile("ci", derandomize=True)
if os.environ.get("CI"):
    settings.load_profile("ci")

from togglecf.data.broad import DataNotFoundError, DatasetIndex, resolve_data_dir

REQUIRE_DATA = os.environ.get("TOGGLECF_REQUIRE_DATA") == "1"
sys.path.insert(0, str(Path(__file__).resolve().parent / "data"))
from make_broad_mini import OUT as MINI_DIR  # noqa: E402  (tests/data/broad_mini, created from BROAD)
from make_broad_mini import ensure as ensure_mini_data  # noqa: E402


def _missing_data(exc):
    if REQUIRE_DATA:
        pytest.fail(f"TOGGLECF_REQUIRE_DATA=1 but BROAD is missing: {exc}")
    pytest.skip(f"BROAD data not available: {exc}")


@pytest.fixture(scope="session")
def broad_index():
    try:
        return DatasetIndex.from_dir(resolve_data_dir())
    except DataNotFoundError as exc:
        _missing_data(exc)


@pytest.fixture(scope="session")
def broad_trial(broad_index):
    """One real trial in HDF5 form with rotation and breaks."""
    return broad_index.load("05_undisturbed_slow_rotation_with_breaks_B")


@pytest.fixture(scope="session")
def mini_index():
    """The mini BROAD directory ``tests/data/broad_mini``: 02, 07 and 24 (4000 samples = 14 s each:
    ~4 s rest, then 10 s of movement; all four motion states occur), cut from the real trials on
    first use (``tests/data/make_broad_mini.py``; BROAD's files are never in the repository)."""
    try:
        return DatasetIndex.from_dir(ensure_mini_data())
    except DataNotFoundError as exc:
        _missing_data(exc)


@pytest.fixture(scope="session")
def mini_trial(mini_index):
    """One short real trial: 24_disturbed_tapping_A (rest, then rotation, linear acceleration and
    taps: every motion state), 4000 samples."""
    return mini_index.load("24_disturbed_tapping_A")


def train_tiny_models(data_dir, trials, out):
    """Train the tiny models (15 + 10 trees of depth 4; no CV, no gains) on ``trials`` into ``out``."""
    from togglecf.run.config import load_config
    from togglecf.run.train import run_training

    cfg = load_config()
    cfg["classifier"].update(n_estimators=15, max_depth=4)
    cfg["regressor"].update(n_estimators=10, max_depth=4)
    cfg["gains"]["learn"] = False
    run_training(cfg, data_dir=data_dir, trials=trials, out=out, cv=False, verbose=False)
    return out


@pytest.fixture(scope="session")
def tiny_model_dir(mini_index, tmp_path_factory):
    """A model directory trained in seconds on the 3 mini trials (cuts of 02, 07, 24; no CV, no
    gains): for tests of what is done *with* trained models (compiled inference, export)."""
    return train_tiny_models(mini_index.root, "02,07,24", tmp_path_factory.mktemp("models") / "tiny")


@pytest.fixture
def rng():
    return np.random.default_rng(12345)


def random_quats(rng, n):
    q = rng.standard_normal((n, 4))
    return q / np.linalg.norm(q, axis=1, keepdims=True)


#: A `togglecf train` config small enough for tests (seconds, not minutes) on a few real trials.
TINY_TRAIN_TOML = """
[run]
cv_folds = 2
[features]
hop_s = 0.1
[classifier]
n_estimators = 8
max_depth = 3
[regressor]
n_estimators = 4
max_depth = 3
[gains]
tau = [17.5, 1.748]
output_tau = [0.0]
bias_tau = [-1.0, 3.498]
mag_disturbance_scale = [0.0]
sweeps = 1
[gains.vqf]
tau_acc = [1.0, 3.0]
tau_mag = [9.0]
bias_sigma_motion = [0.1]
confidence_floor = [0.0]
noise_weight_acc = [0.0]
noise_weight_mag = [0.0]
sweeps = 1
"""
