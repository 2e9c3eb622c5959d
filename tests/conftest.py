"""Shared fixtures. Real-data tests are marked ``broad``: skipped with the reason when BROAD is
absent, except when ``TOGGLECF_REQUIRE_DATA=1`` (set by .ci/run), where absence is an error."""
import os

import numpy as np
import pytest

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


@pytest.fixture
def rng():
    return np.random.default_rng(12345)


def random_quats(rng, n):
    q = rng.standard_normal((n, 4))
    return q / np.linalg.norm(q, axis=1, keepdims=True)
