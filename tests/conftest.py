"""Shared fixtures. Real-data tests are marked ``broad``: skipped with the reason when BROAD is
absent, except when ``TOGGLECF_REQUIRE_DATA=1`` (set by .ci/run), where absence is an error."""
import os

import numpy as np
import pytest
from hypothesis import settings

# CI: the same examples every run (a failure is reproducible); locally hypothesis explores anew
settings.register_profile("ci", derandomize=True)
if os.environ.get("CI"):
    settings.load_profile("ci")

from togglecf.data import DataNotFoundError, DatasetIndex, resolve_data_dir

REQUIRE_DATA = os.environ.get("TOGGLECF_REQUIRE_DATA") == "1"


@pytest.fixture(scope="session")
def broad_index():
    try:
        return DatasetIndex.from_dir(resolve_data_dir())
    except DataNotFoundError as exc:
        if REQUIRE_DATA:
            pytest.fail(f"TOGGLECF_REQUIRE_DATA=1 but BROAD is missing: {exc}")
        pytest.skip(f"BROAD data not available: {exc}")


@pytest.fixture(scope="session")
def broad_trial(broad_index):
    """One real trial in HDF5 form with rotation and breaks."""
    return broad_index.load("05_undisturbed_slow_rotation_with_breaks_B")


@pytest.fixture(scope="session")
def tiny_model_dir(broad_index, tmp_path_factory):
    """A model directory trained in seconds on 3 real trials (02, 07, 24; no CV, no gains):
    for tests of what is done *with* trained models (compiled inference, export)."""
    from togglecf.train import load_config, run_training

    cfg = load_config()
    cfg["classifier"].update(n_estimators=15, max_depth=4)
    cfg["regressor"].update(n_estimators=10, max_depth=4)
    cfg["gains"]["learn"] = False
    out = tmp_path_factory.mktemp("models") / "tiny"
    run_training(cfg, data_dir=broad_index.root, trials="02,07,24", out=out, cv=False, verbose=False)
    return out


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
alpha = [0.0002, 0.002]
gamma = [1.0]
bias_gain = [0.0, 0.001]
mag_disturbance_scale = [0.0]
sweeps = 1
"""
