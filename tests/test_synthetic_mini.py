"""The synthetic stand-in for the mini BROAD cuts (``tests/data/make_synthetic_mini.py``) and the choice
between the two (``tests/data/mini_data.py``): BROAD's layout, every motion state in every pair of
trials, the same bytes for the same seed, and the fallback rules of ``TOGGLECF_MINI``."""
import json

import h5py
import numpy as np
import pytest

import make_broad_mini
import make_synthetic_mini
import mini_data
from togglecf import simulate as sim
from togglecf.data.broad import DataNotFoundError, DatasetIndex


def test_translation_moves_position_and_acceleration_agree():
    fs = 2000.0 / 7.0
    pos, acc = sim.translation_moves(2000, fs, [(1.0, 0.5, (0.3, -0.1, 0.05)), (3.0, 0.8, (-0.3, 0.1, 0.0))])
    second_diff = (pos[2:] - 2 * pos[1:-1] + pos[:-2]) * fs ** 2
    # the central difference is exact up to O(Δt²) inside a move, but the jerk jumps to 60|d|/T³ (~144 m/s³
    # here) where a move starts and ends: there it is off by ~jerk·Δt/6 ≈ 0.03 m/s², against peaks of ~7 m/s²
    np.testing.assert_allclose(second_diff, acc[1:-1], atol=0.05)
    inner = np.ones(len(second_diff), bool)
    for k in (285, 428, 857, 1085):  # the samples next to a start or an end
        inner[k - 3:k + 3] = False
    np.testing.assert_allclose(second_diff[inner], acc[1:-1][inner], atol=2e-3)
    assert np.abs(acc).max() > 5.0
    np.testing.assert_allclose(pos[-1], pos[0] + [0.0, 0.0, 0.05], atol=1e-12)  # both moves completed


def test_synthetic_trials_layout_states_and_determinism(tmp_path):
    a, b = tmp_path / "a", tmp_path / "b"
    make_synthetic_mini.make(a)
    make_synthetic_mini.make(b)
    for f in sorted(p.name for p in a.iterdir()):
        assert (a / f).read_bytes() == (b / f).read_bytes(), f  # same seed, same bytes
    index = json.loads((a / "trials.json").read_text())
    assert set(index) == {"groups", "trials"} and len(index["groups"]) == 16
    idx = DatasetIndex.from_dir(a)
    assert idx.select("02,07,24") == list(make_synthetic_mini.TRIALS) and not idx.missing
    for name in idx.available:
        assert "synthetic" in name
        with h5py.File(idx.available[name], "r") as f:
            assert set(f) == set(make_broad_mini.FIELDS)
            assert "SYNTHETIC" in f.attrs["info"] and "make_synthetic_mini.py" in f.attrs["info"]
        t = idx.load(name)
        assert t.n_samples == 4000 and t.fs == pytest.approx(285.714, abs=1e-3)
        assert np.argmax(t.movement) == 1143 and t.movement[1143:].all()  # 4 s of rest, then movement
    counts = make_synthetic_mini.check(a)  # asserts every state in every pair
    assert all(c.sum() > 3000 for c in counts.values())  # labels defined on most samples


def test_mini_dir_rules(tmp_path, monkeypatch):
    def no_broad(out):
        raise DataNotFoundError("no BROAD here")

    monkeypatch.setattr(mini_data, "SYNTHETIC_DIR", tmp_path / "synthetic_mini")
    monkeypatch.setattr(mini_data.make_broad_mini, "ensure", no_broad)
    monkeypatch.delenv("TOGGLECF_REQUIRE_DATA", raising=False)
    monkeypatch.delenv("TOGGLECF_MINI", raising=False)
    assert mini_data.mini_dir() == ("synthetic", tmp_path / "synthetic_mini")  # no BROAD: the fallback
    assert (tmp_path / "synthetic_mini" / "trials.json").is_file()
    assert not (tmp_path / "synthetic_mini.partial").exists()
    monkeypatch.setenv("TOGGLECF_REQUIRE_DATA", "1")
    with pytest.raises(DataNotFoundError):  # CI: the real cuts are required ...
        mini_data.mini_dir()
    monkeypatch.setenv("TOGGLECF_MINI", "synthetic")  # ... unless the synthetic ones are asked for
    assert mini_data.mini_dir()[0] == "synthetic"
    monkeypatch.delenv("TOGGLECF_REQUIRE_DATA")
    monkeypatch.setenv("TOGGLECF_MINI", "broad")
    with pytest.raises(DataNotFoundError):
        mini_data.mini_dir()
    monkeypatch.setenv("TOGGLECF_MINI", "real")
    with pytest.raises(ValueError, match="TOGGLECF_MINI"):
        mini_data.mini_dir()
    monkeypatch.setenv("TOGGLECF_MINI", "auto")
    monkeypatch.setattr(mini_data.make_broad_mini, "ensure", lambda out: tmp_path / "broad_mini")
    assert mini_data.mini_dir() == ("broad", tmp_path / "broad_mini")  # BROAD found: the real cuts
