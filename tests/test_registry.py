"""The filter registry (``FilterSpec``): every filter by name, the trained toggling filter
included, validated without a sampling rate; compiled models cached by content."""
import argparse
import importlib
import json
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from togglecf.filters import FILTERS, MadgwickFilter
from togglecf.core.io import file_sha256
from togglecf.core.extras import MissingExtraError, missing_extra_message
from togglecf import simulate as sim
from togglecf.registry import (CATALOG, CLASSIC_NAMES, FILTER_NAMES, LEARNED_VQF, REFERENCE_VQF, TOGGLING, TRAINED,
                               VQF_TOGGLING, FilterEntry, FilterSpec, ReferenceVQF, filter_spec)
from togglecf.toggling.pretrained import PRETRAINED_FILE, LearnedVQF
from togglecf.run.config import load_config
from togglecf.run.train import run_training
from togglecf.toggling import load_toggling_filter, model_dir_digest


PIPELINES = Path(__file__).resolve().parents[1] / "pipelines"


def test_names_cover_classic_filters_and_toggling():
    assert set(FILTER_NAMES) == set(FILTERS) | set(TRAINED) | {LEARNED_VQF, REFERENCE_VQF} and TOGGLING in TRAINED


def _kind(kind):
    return tuple(n for n, e in CATALOG.items() if e.kind == kind)


def _choices_of_filter_options():
    """{(command, option): choices} of every ``--filter``-like option with choices in the CLI's parser."""
    from togglecf.cli.parsers import build_parser

    out = {}
    sub = next(a for a in build_parser()._actions if isinstance(a, argparse._SubParsersAction))
    for command, parser in sub.choices.items():
        for action in parser._actions:
            if action.choices is not None and any(o.startswith("--filter") for o in action.option_strings):
                out[(command, action.option_strings[0])] = tuple(action.choices)
    return out


def test_one_table_feeds_the_names_the_cli_the_docs_and_the_study(tmp_path):
    """``CATALOG`` is the one list of filters: the registry's names, ``filters.FILTERS``, the CLI's choices,
    the docs' table of defaults and the study report's labels are read from it."""
    assert FILTER_NAMES == tuple(CATALOG) and all(isinstance(e, FilterEntry) and e.name == n for n, e in CATALOG.items())
    assert CLASSIC_NAMES == _kind("classic") and TRAINED == _kind("trained") == (TOGGLING, VQF_TOGGLING)
    assert _kind("pretrained") == (LEARNED_VQF,) and _kind("reference") == (REFERENCE_VQF,)
    assert list(FILTERS.items()) == [(n, CATALOG[n].cls) for n in CLASSIC_NAMES]  # the ML-free view, same order
    assert all(e.label and e.description and "\n" not in e.description for e in CATALOG.values())

    choices = _choices_of_filter_options()
    assert ("evaluate", "--filter") in choices and ("tune", "--filter") in choices
    for (command, option), names in choices.items():
        assert names == {"tune": CLASSIC_NAMES, "export": TRAINED}.get(command, FILTER_NAMES), (command, option)
    from togglecf.cli.filter_list import filter_names  # --filters LIST
    assert filter_names(",".join(FILTER_NAMES)) == list(FILTER_NAMES)
    with pytest.raises(ValueError, match="unknown filter"):
        filter_names("madgwick,nofilter")

    sys.path.insert(0, str(PIPELINES))
    try:
        regenerate_docs = importlib.import_module("regenerate_docs")
    finally:
        sys.path.remove(str(PIPELINES))
    regenerate_docs.filter_defaults(tmp_path, "cmd")
    rows = [r for r in (tmp_path / "filter_defaults.md").read_text().splitlines() if r.startswith("| `")]
    assert [r.split("|")[1].strip().strip("`") for r in rows] == list(CLASSIC_NAMES)
    assert [r.split("|")[2].strip() for r in rows] == [CATALOG[n].description for n in CLASSIC_NAMES]

    from togglecf.report.study_report import LABELS, MAIN_FILTERS, OTHER_ROWS
    assert set(LABELS) == set(MAIN_FILTERS) and set(MAIN_FILTERS) - set(CATALOG) == set(OTHER_ROWS)
    for f in set(MAIN_FILTERS) & set(CATALOG):
        assert LABELS[f].startswith(CATALOG[f].label + " "), f


def test_a_bad_table_row_is_refused():
    with pytest.raises(ValueError, match="kind"):
        FilterEntry("x", "learned", "X", "x")
    with pytest.raises(ValueError, match="class"):
        FilterEntry("madgwick", "classic", "Madgwick", "no class given")
    with pytest.raises(ValueError, match="class"):
        FilterEntry("toggling", "trained", "toggling CF", "a class given", MadgwickFilter)
    with pytest.raises(ValueError, match="named"):
        FilterEntry("beta", "classic", "Madgwick", "the class's name differs", MadgwickFilter)


def test_the_pretrained_filter_needs_no_models_and_takes_none():
    spec = FilterSpec(LEARNED_VQF, use_mag=False)
    f = spec.build(100.0)
    assert isinstance(f, LearnedVQF) and f.fs == 100.0 and not f.use_mag
    assert spec.identity() == file_sha256(PRETRAINED_FILE)  # results journaled with it follow the shipped file
    assert spec.settings == f.settings
    with pytest.raises(ValueError, match="pretrained model the package ships"):
        FilterSpec(LEARNED_VQF, params={"tau_acc": 1.0})
    with pytest.raises(ValueError, match="takes a portable model file"):  # a model directory is vqf_toggling's
        FilterSpec(LEARNED_VQF, models="somewhere")


def test_the_learned_vqf_runs_a_portable_file(tmp_path):
    """``--models FILE.npz`` with learned_vqf: that file's settings and models, its identity its content."""
    import shutil
    copy = shutil.copy(PRETRAINED_FILE, tmp_path / "mine.npz")
    spec = FilterSpec(LEARNED_VQF, models=str(copy))
    assert spec.identity() == file_sha256(copy) and spec.as_params() == {"models": str(copy)}
    assert filter_spec(LEARNED_VQF, spec.as_params()) == spec  # how a sweep's workers rebuild it
    assert spec.build(100.0).settings == spec.settings
    with pytest.raises(FileNotFoundError, match="no such model file"):
        FilterSpec(LEARNED_VQF, models=str(tmp_path / "missing.npz"))


def test_classic_specs_validate_without_a_rate():
    spec = FilterSpec("madgwick", {"beta": 0.05})
    assert spec.settings.beta == 0.05
    for bad, msg in ((FilterSpec, "unknown filter"),):
        with pytest.raises(ValueError, match=msg):
            bad("no_such_filter")
    with pytest.raises(ValueError, match="unknown setting"):
        FilterSpec("madgwick", {"gamma": 1.0})
    with pytest.raises(ValueError, match="tau must be finite"):
        FilterSpec("cf", {"tau": float("nan")})  # the settings' own range check, no filter built
    with pytest.raises(ValueError, match="--models is for"):
        FilterSpec("cf", models="somewhere")


@pytest.mark.parametrize("fs", [50.0, 285.714])
def test_build_at_any_rate(fs):
    f = FilterSpec("madgwick", {"beta": 0.05}, use_mag=False).build(fs)
    assert isinstance(f, MadgwickFilter) and f.fs == fs and not f.use_mag and f.settings.beta == 0.05


def test_toggling_spec_needs_a_trained_directory(tmp_path):
    with pytest.raises(ValueError, match="needs a model directory"):
        FilterSpec(TOGGLING)
    with pytest.raises(ValueError, match="no --param"):
        FilterSpec(TOGGLING, {"tau_acc": 0.1}, models=tmp_path)
    with pytest.raises(FileNotFoundError, match="no learned gains"):
        FilterSpec(TOGGLING, models=tmp_path)
    with pytest.raises(ValueError, match="sweep's parameter dict|model directory"):
        filter_spec(TOGGLING, {})


def _train(mini_index, out, n_estimators):
    cfg = load_config()
    cfg["classifier"].update(n_estimators=n_estimators, max_depth=3)
    cfg["regressor"].update(n_estimators=3, max_depth=3)
    cfg["gains"].update(tau=[17.5, 1.748], output_tau=[0.0], bias_tau=[-1.0], mag_disturbance_scale=[0.0], sweeps=1,
                        modes=["9d"])
    run_training(cfg, data_dir=mini_index.root, trials="02,07,24", out=out, cv=False, verbose=False)


def test_retrained_directory_is_not_served_from_the_cache(mini_index, mini_names, tmp_path):
    """Defect of issue 14: the compiled-model cache was keyed on the path, so a directory
    retrained in place ran old trees with new gains. It is keyed on the content now."""
    d = tmp_path / "models"
    _train(mini_index, d, n_estimators=4)
    first = load_toggling_filter(d, 100.0)
    digest = model_dir_digest(d)
    n_first = first.models.forest.n_nodes
    shutil.rmtree(d)
    _train(mini_index, d, n_estimators=9)  # same path, other trees
    second = load_toggling_filter(d, 100.0)
    assert model_dir_digest(d) != digest
    assert second.models.forest.n_nodes != n_first
    assert FilterSpec(TOGGLING, models=d).identity() == model_dir_digest(d)
    meta = json.loads((d / "metadata.json").read_text())
    assert meta["classifier_params"]["n_estimators"] == 9
    t = mini_index.load(mini_names[1])  # 07
    q = second.update_batch(t.gyr, t.acc, t.mag).quat
    assert np.all(np.isfinite(q))


@pytest.mark.parametrize("use_mag", [True, False])
def test_vqf_is_the_reference_package_at_its_defaults(use_mag):
    """``vqf``: the package's ``VQF(1/fs).updateBatch`` as the study runs it, sample by sample the same."""
    vqf = pytest.importorskip("vqf")
    fs = 100.0
    trial = sim.imu_from_orientation(sim.gimbal_trajectory(fs, 3.0), fs)
    spec = FilterSpec(REFERENCE_VQF, use_mag=use_mag)
    f = spec.build(fs)
    assert isinstance(f, ReferenceVQF) and f.fs == fs
    out = f.update_batch(trial.gyr, trial.acc, trial.mag if use_mag else None)
    ref = vqf.VQF(1.0 / fs).updateBatch(trial.gyr, trial.acc, trial.mag if use_mag else None)
    np.testing.assert_array_equal(out.quat, ref["quat9D" if use_mag else "quat6D"])
    g = spec.build(fs)
    q = [g.update(trial.gyr[i], trial.acc[i], trial.mag[i] if use_mag else None, dt=1.01 / fs) for i in range(50)]
    np.testing.assert_allclose(q, out.quat[:50], atol=1e-12)
    assert spec.settings.params["tauAcc"] == vqf.VQF(0.01).params["tauAcc"] and "at its defaults" in str(spec.settings)
    assert spec.identity().startswith("vqf ")  # journaled results follow the package version
    for kw in ({"params": {"tauAcc": 1.0}}, {"models": "somewhere"}):
        with pytest.raises(ValueError, match="reference VQF at its defaults"):
            FilterSpec(REFERENCE_VQF, **kw)
    with pytest.raises(ValueError, match="fixed sampling time"):  # an irregular log: not run at a wrong rate
        f.update_batch(trial.gyr, trial.acc, trial.mag if use_mag else None, dt=np.full(trial.n_samples, 2 / fs))


def test_vqf_without_the_package_is_one_line_naming_the_extra(monkeypatch):
    monkeypatch.setitem(sys.modules, "vqf", None)  # as if it were not installed
    with pytest.raises(MissingExtraError) as exc:
        FilterSpec(REFERENCE_VQF)
    assert str(exc.value) == missing_extra_message("vqf", "the vqf filter (the reference VQF, dlaidig/vqf)")
    assert str(exc.value).endswith("pip install 'togglecf[vqf]'")


def test_the_registry_does_not_import_vqf():
    code = "import sys, togglecf.registry; print('vqf' in sys.modules)"
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert res.returncode == 0 and res.stdout.strip() == "False", res.stderr[-2000:]
