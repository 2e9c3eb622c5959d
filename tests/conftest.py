"""Shared fixtures. Real-data tests are marked ``broad``: skipped with the reason when BROAD is
absent, except when ``TOGGLECF_REQUIRE_DATA=1`` (set by .ci/run), where absence is an error.

``mini_index``: three short trials (02, 07, 24; 4000 samples each) for the tests of what the code does
with trials that make no claim about the full dataset (models, export, C filter): the 14-s cuts of
real BROAD trials in ``tests/data/broad_mini`` when BROAD is found (made on first use, never
committed), otherwise synthetic trials in BROAD's layout in ``tests/data/synthetic_mini``
(``TOGGLECF_MINI=synthetic`` forces them; see ``tests/data/README.md`` and ``tests/data/mini_data.py``).
``mini_kind`` says which ("broad" or "synthetic"): an assertion about a number measured on the real
recordings holds only for "broad"."""
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
from togglecf.run.config import load_config
from togglecf.run.train import run_training
from togglecf.toggling.gains import save_gains
from togglecf.toggling.load import load_compiled_models

REQUIRE_DATA = os.environ.get("TOGGLECF_REQUIRE_DATA") == "1"
sys.path.insert(0, str(Path(__file__).resolve().parent / "data"))
from mini_data import mini_dir  # noqa: E402  (tests/data/broad_mini from BROAD, or tests/data/synthetic_mini)


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


_MINI = {}


def _mini():
    """``(kind, DatasetIndex)`` of the mini directory (chosen once per session, ``mini_data.mini_dir``)."""
    if not _MINI:
        try:
            kind, root = mini_dir()
        except DataNotFoundError as exc:
            _missing_data(exc)
        _MINI.update(kind=kind, index=DatasetIndex.from_dir(root))
    return _MINI["kind"], _MINI["index"]


@pytest.fixture(scope="session")
def mini_index():
    """The mini directory: 02, 07 and 24, 4000 samples = 14 s each (~4 s rest, then 10 s of
    movement; all four motion states occur in every pair). The real cuts (``tests/data/broad_mini``,
    from BROAD on first use; BROAD's files are never in the repository) when BROAD is found, else
    the synthetic trials (``tests/data/synthetic_mini``); ``mini_kind`` says which."""
    return _mini()[1]


@pytest.fixture(scope="session")
def mini_kind(mini_index):
    """``"broad"`` (real cuts) or ``"synthetic"`` (simulator output): which data ``mini_index`` holds."""
    return _mini()[0]


def mini_name(index, prefix: str) -> str:
    """The one trial of ``index`` whose name starts with ``prefix`` (``"24"`` or ``"24_"``)."""
    prefix = prefix if prefix.endswith("_") else prefix + "_"
    hits = [n for n in index.available if n.startswith(prefix)]
    assert len(hits) == 1, (prefix, list(index.available))
    return hits[0]


@pytest.fixture(scope="session")
def mini_names(mini_index):
    """The names of the three mini trials in the order 02, 07, 24."""
    return [mini_name(mini_index, p) for p in ("02", "07", "24")]


@pytest.fixture(scope="session")
def mini_trial(mini_index):
    """One short trial, the one starting with ``24_`` (real: 24_disturbed_tapping_A; synthetic:
    24_synthetic_tapping): rest, then rotation, linear acceleration and taps (every motion state),
    4000 samples."""
    return mini_index.load(mini_name(mini_index, "24"))


def train_tiny_models(data_dir, trials, out):
    """Train the tiny models (15 + 10 trees of depth 4; no CV, no gains) on ``trials`` into ``out``."""

    cfg = load_config()
    cfg["classifier"].update(n_estimators=15, max_depth=4)
    cfg["regressor"].update(n_estimators=10, max_depth=4)
    cfg["gains"]["learn"] = False
    run_training(cfg, data_dir=data_dir, trials=trials, out=out, cv=False, verbose=False)
    return out


def with_fixed_gains(model_dir, settings_for, trials=("fixed-in-test",)):
    """Store fixed (not learned) gains in ``model_dir`` for 9D and 6D and return it:
    ``settings_for(class_names, static_state, use_mag)`` gives the settings, or a tuple of settings
    (one per learned filter kind)."""

    m = load_compiled_models(model_dir)
    for use_mag in (True, False):
        given = settings_for(m.class_names, m.static_state, use_mag)
        for one in given if isinstance(given, tuple) else (given,):
            save_gains(model_dir, one, list(trials), [], use_mag=use_mag, predictions="none (fixed in the test)")
    return model_dir


@pytest.fixture(scope="session")
def tiny_model_dir(mini_index, tmp_path_factory):
    """A model directory trained in seconds on the 3 mini trials (02, 07, 24; no CV, no gains): for tests of what is done *with* trained models (compiled inference, export)."""
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
mag_rate_limit = [0.0, 0.02]
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


# ------------------------------------------------------------------ C exports at another rate
#: the real 100 Hz recording the C exports are run on at a rate other than the models'
RATE_PHONE_TRIAL = "Jakob_Nexus5_NoDist_AR"


def _resampled(t, fs_new):
    """``t`` linearly interpolated onto a ``fs_new`` [Hz] grid (gyr, acc, mag; a test input only: C and
    Python get the same arrays)."""
    t_old = np.arange(t.n_samples) / t.fs
    t_new = np.arange(0.0, t_old[-1], 1.0 / fs_new)
    return tuple(np.column_stack([np.interp(t_new, t_old, x[:, j]) for j in range(3)]) for x in (t.gyr, t.acc, t.mag))


@pytest.fixture(scope="module", params=[pytest.param("phone100", marks=pytest.mark.broad),
                                        pytest.param("broad200", marks=pytest.mark.broad)])
def other_rate(request, broad_index):
    """A real trial at a rate other than the models' (285.714 Hz): a 100 Hz phone recording
    (tyrex_nexus5, Nexus 5, no disturbance, AR) or BROAD trial 05 resampled to 200 Hz."""
    if request.param == "phone100":
        phone = broad_index.root.parent / "tyrex_nexus5"
        if not (phone / "trials.json").is_file():
            pytest.skip(f"no phone dataset at {phone}")
        t = DatasetIndex.from_dir(phone).load(RATE_PHONE_TRIAL)
        assert t.fs == pytest.approx(100.0)
        return request.param, 100.0, t.gyr, t.acc, t.mag
    return (request.param, 200.0, *_resampled(broad_index.load("05_undisturbed_slow_rotation_with_breaks_B"), 200.0))
