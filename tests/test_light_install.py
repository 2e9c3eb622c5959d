"""A light install: ``pip install togglecf`` (numpy, scipy, numba) runs every filter and a trained model
directory's filter in the loop; the rest are extras (``togglecf.core.extras``, pyproject.toml), and a
missing one is one line naming it, never a traceback. The light install is imitated in a fresh
interpreter in which the optional packages cannot be imported (a ``sys.meta_path`` finder refuses
them as if they were not installed)."""
import json
import re
import shutil
import subprocess
import sys
import textwrap
import tomllib
from pathlib import Path

import numpy as np
import pytest
from conftest import with_fixed_gains

from togglecf.cli.main import main
from togglecf.core.extras import EXTRAS, MissingExtraError, check_extra, deferred, missing_extra_message, require
from togglecf.filters.vqf_toggling import VQFTogglingSettings
from togglecf.learn.compiled import INLOOP_FILE, CompiledModels
from togglecf.learn.models import load_bundle
from togglecf.learn.trees import FlatForest
from togglecf.registry import FILTER_NAMES, REFERENCE_VQF
from togglecf.toggling import load_compiled_models
from togglecf.toggling.gains import GainSearch
from togglecf.toggling.pretrained import PRETRAINED_FILE

ROOT = Path(__file__).resolve().parents[1]
#: what the extras install (top-level module names); none of it may be needed by a light install
HEAVY = ("xgboost", "sklearn", "pandas", "matplotlib", "mpl_toolkits", "treelite", "tl2cgen", "tqdm",
         "serial", "dask", "distributed", "vqf", "unicorn", "capstone")

_PRELUDE = """
import importlib.abc, json, sys
BLOCKED = {blocked!r}
class _NotInstalled(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path=None, target=None):
        if name.split(".")[0] in BLOCKED:
            raise ModuleNotFoundError(f"No module named {{name!r}}", name=name)
sys.meta_path.insert(0, _NotInstalled())
"""


def _python(code: str, *args, blocked=HEAVY, cwd=None, timeout=900):
    """``code`` in a fresh interpreter where the modules ``blocked`` are not installed."""
    return subprocess.run([sys.executable, "-c", _PRELUDE.format(blocked=tuple(blocked)) + textwrap.dedent(code),
                           *map(str, args)], capture_output=True, text=True, timeout=timeout, cwd=cwd)


@pytest.fixture(scope="module")
def model_dir(tiny_model_dir, tmp_path_factory):
    """The tiny models (``togglecf train`` on the mini trials) with fixed gains of both learned filters."""
    d = tmp_path_factory.mktemp("light") / "m"
    shutil.copytree(tiny_model_dir, d)

    def settings(classes, static, use_mag):
        return (GainSearch().start(classes, static),
                VQFTogglingSettings(states=tuple(classes), tau_acc_states=tuple(1.0 + i for i in range(len(classes))),
                                    mag_disturbance_scale=10.0 if use_mag else 0.0, modulation_tau=3.0))
    return with_fixed_gains(d, settings)


# ------------------------------------------------------------------- the light install runs the filters

def test_every_filter_and_a_trained_model_run_without_the_extras(model_dir, tmp_path):
    """Every filter of the registry, the trained ones from a model directory (``load_toggling_filter``,
    ``FilterSpec``), and ``togglecf stream --input`` with the learned filter, none of the extras importable;
    the Python API's optional parts raise an ImportError naming their extra."""
    hdf5 = next((ROOT / "tests" / "data").glob("*_mini/*.hdf5"))
    res = _python("""
        import numpy as np
        import togglecf.simulate as sim
        from togglecf.cli.main import main
        from togglecf.registry import FILTER_NAMES, TRAINED, FilterSpec
        from togglecf.toggling import load_toggling_filter

        model_dir, out_dir, hdf5 = sys.argv[1:4]
        fs = 100.0
        trial = sim.imu_from_orientation(sim.gimbal_trajectory(fs, 3.0), fs)
        ran, errors = {}, {}
        for name in FILTER_NAMES:
            for use_mag in (True, False):
                try:
                    f = FilterSpec(name, models=model_dir if name in TRAINED else None, use_mag=use_mag).build(fs)
                except ImportError as exc:  # the reference VQF is an extra: refused when named
                    errors[name] = str(exc)
                    continue
                q = f.update_batch(trial.gyr, trial.acc, trial.mag if use_mag else None).quat
                assert q.shape == (trial.n_samples, 4) and np.all(np.isfinite(q)), name
                ran[name] = ran.get(name, 0) + 1
        for kind in TRAINED:
            out = load_toggling_filter(model_dir, fs, kind=kind).update_batch(trial.gyr, trial.acc, trial.mag)
            assert np.all(np.isfinite(out.quat)) and np.nanmean(out.diagnostics["fallback"]) < 1, kind
        # the command line: a learned filter on IMU lines from a file
        csv = f"{out_dir}/imu.csv"
        rows = np.column_stack([np.arange(trial.n_samples) / fs, trial.gyr, trial.acc, trial.mag])
        np.savetxt(csv, rows, delimiter=",", header="t,gx,gy,gz,ax,ay,az,mx,my,mz", comments="")
        assert main(["stream", "--input", csv, "--filter", "toggling", "--models", model_dir, "--fs", "100",
                     "--rate", "0"]) == 0
        # the optional parts: one ImportError line naming the extra
        from togglecf.data.broad import load_trial
        from togglecf.learn.models import load_bundle
        from togglecf.report import plots
        assert load_trial(hdf5).n_samples > 0  # h5py is a dependency: a trial file loads without extras
        for what, call in (("load_bundle", lambda: load_bundle(model_dir)),
                           ("plot", lambda: plots.plot_euler(trial, {"cf": trial.opt_quat}))):
            try:
                call()
            except ImportError as exc:
                errors[what] = str(exc)
        loaded = sorted(m for m in sys.modules if m.split(".")[0] in BLOCKED)
        print("RESULT " + json.dumps({"ran": ran, "errors": errors, "loaded": loaded}))
    """, model_dir, tmp_path, hdf5, cwd=tmp_path)
    assert res.returncode == 0, res.stderr[-4000:]
    out = json.loads(next(ln for ln in res.stdout.splitlines() if ln.startswith("RESULT "))[7:])
    assert sorted(out["ran"]) == sorted(set(FILTER_NAMES) - {REFERENCE_VQF}) and set(out["ran"].values()) == {2}
    assert out["loaded"] == []
    assert out["errors"] == {
        REFERENCE_VQF: missing_extra_message("vqf", "the vqf filter (the reference VQF, dlaidig/vqf)"),
        "load_bundle": missing_extra_message("train", f"reading the XGBoost models of {model_dir}"),
        "plot": missing_extra_message("plot", "togglecf.report.plots")}
    lines = [ln for ln in res.stdout.splitlines() if not ln.startswith("RESULT ")]
    assert lines[0] == "t,qw,qx,qy,qz,roll_deg,pitch_deg,yaw_deg" and len(lines) == 1 + 300


def test_the_stored_forest_is_the_boosters_forest(model_dir):
    """``togglecf train`` stores the flat forest (read without XGBoost): bit for bit the forest
    flattened from the XGBoost files, with the same settings and ranges."""
    stored = CompiledModels.stored(model_dir)
    flat = CompiledModels.from_bundle(load_bundle(model_dir))
    for name in ("feature", "threshold", "left", "right", "default_left", "value", "roots", "tree_group",
                 "base_margin"):
        a, b = getattr(stored.forest, name), getattr(flat.forest, name)
        assert a.dtype == b.dtype and np.array_equal(a, b), name
    assert (stored.forest.link, stored.forest.n_features) == (flat.forest.link, flat.forest.n_features)
    assert stored.class_names == flat.class_names and stored.schema_hash == flat.schema_hash
    assert stored.feature_settings == flat.feature_settings
    assert np.array_equal(stored.feature_low, flat.feature_low, equal_nan=True)
    assert np.array_equal(stored.feature_high, flat.feature_high, equal_nan=True)
    assert stored.max_out_of_range == flat.max_out_of_range
    assert FlatForest.from_dict(json.loads(json.dumps(flat.forest.to_dict()))).to_dict() == flat.forest.to_dict()


def test_a_damaged_stored_forest_is_refused_and_an_old_directory_uses_the_boosters(model_dir, tmp_path):
    bad = tmp_path / "bad"
    shutil.copytree(model_dir, bad)
    (bad / INLOOP_FILE).write_bytes((bad / INLOOP_FILE).read_bytes().replace(b"[", b"[ ", 1))
    with pytest.raises(ValueError, match="sha256 differs from metadata.json"):
        CompiledModels.stored(bad)
    old = tmp_path / "old"
    shutil.copytree(model_dir, old)
    meta = json.loads((old / "metadata.json").read_text())
    del meta["inloop_forest"]
    (old / "metadata.json").write_text(json.dumps(meta))
    (old / INLOOP_FILE).unlink()
    assert CompiledModels.stored(old) is None
    assert np.array_equal(load_compiled_models(old).forest.threshold, CompiledModels.stored(model_dir).forest.threshold)


# ------------------------------------------------------------ a missing extra: one line, no traceback

@pytest.mark.parametrize("argv,blocked,extra", [
    (["train", "--trials", "02,07", "--out", "m"], ("xgboost",), "train"),
    (["export", "--models", "m", "--out", "e", "--no-check"], ("treelite", "tl2cgen"), "export"),
    (["plot", "euler", "--trial", "05", "--out", "e.png"], ("matplotlib",), "plot"),
    (["evaluate", "--filter", "madgwick"], ("pandas",), "data"),
    (["stream", "--port", "/dev/null", "--fs", "100"], ("serial",), "stream"),
    (["train", "--trials", "02,07", "--out", "m", "--backend", "dask"], ("distributed",), "dask"),
], ids=["train", "export", "plot", "evaluate", "stream", "dask"])
def test_a_command_without_its_extra_says_which_in_one_line(argv, blocked, extra, tmp_path):
    res = _python("from togglecf.cli.main import main\nsys.exit(main(sys.argv[1:]))", *argv, blocked=blocked,
                  cwd=tmp_path)
    what = {"stream": "togglecf stream --port", "dask": "--backend dask"}.get(extra, f"togglecf {argv[0]}")
    assert res.returncode == 1
    assert res.stderr.strip() == f"{what} needs the [{extra}] extra: pip install 'togglecf[{extra}]'"
    assert "Traceback" not in res.stderr + res.stdout


def test_the_python_api_raises_an_import_error_naming_the_extra(monkeypatch):
    monkeypatch.setitem(sys.modules, "xgboost", None)  # import of xgboost fails as if it were not installed
    with pytest.raises(ImportError) as exc:
        require("xgboost", extra="train", what="togglecf train")
    assert str(exc.value) == "togglecf train needs the [train] extra: pip install 'togglecf[train]'"
    with pytest.raises(MissingExtraError, match=r"\[train\] extra"):
        check_extra("train", what="togglecf train")
    xgb = deferred("xgboost", extra="train", what="togglecf train")  # binding it needs nothing
    with pytest.raises(MissingExtraError, match=r"\[train\] extra"):
        xgb.Booster
    assert require("numpy", extra="data", what="x") is np
    with pytest.raises(ValueError, match="unknown extra"):
        deferred("numpy", extra="nope", what="x")


# ------------------------------------------------------------------------- the command line starts light

def test_help_imports_no_optional_package_and_no_numba():
    res = _python("""
        from togglecf.cli.main import main
        try:
            main(["--help"])
        except SystemExit as exc:
            assert exc.code == 0
        print("LOADED " + json.dumps(sorted({m.split(".")[0] for m in sys.modules})))
    """, blocked=())
    assert res.returncode == 0, res.stderr
    loaded = set(json.loads(next(ln for ln in res.stdout.splitlines() if ln.startswith("LOADED "))[7:]))
    assert "evaluate" in res.stdout and "prune" in res.stdout
    assert not loaded & set(HEAVY)
    assert not loaded & {"numba", "scipy", "llvmlite", "h5py"}  # nothing compiled or read to list the commands


@pytest.mark.parametrize("argv", [["trials"], ["evaluate"], ["tune"], ["train"], ["plot", "euler"], ["plot", "error"],
                                  ["plot", "3d"], ["stream"], ["export"], ["prune"], ["download"]])
def test_every_subcommand_has_its_help(argv, capsys):
    with pytest.raises(SystemExit) as exc:
        main([*argv, "--help"])
    assert exc.value.code == 0
    out = capsys.readouterr().out
    assert out.startswith(f"usage: togglecf {' '.join(argv)}")
    if argv[0] in ("evaluate", "stream"):
        assert "madgwick" in out and "vqf_toggling" in out  # the registry's names, read for the help
    if argv[0] in ("train", "stream", "prune"):
        assert "default" in out


# ------------------------------------------------------------------------ extras and pyproject.toml agree

#: distribution name in pyproject.toml -> the module it installs
_MODULE_OF = {"scikit-learn": "sklearn", "pyserial": "serial"}


def _extras_in_pyproject() -> dict:
    """extra -> the top-level modules it installs, the extras it includes expanded."""
    deps = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["optional-dependencies"]

    def modules(extra, seen=()):
        out = set()
        for req in deps[extra]:
            name = req.split(";")[0].split(">")[0].split("<")[0].split("=")[0].strip()
            base, _, inner = name.partition("[")
            if base == "togglecf":
                for e in inner.rstrip("]").split(","):
                    out |= modules(e.strip(), seen + (extra,))
            else:
                out.add(_MODULE_OF.get(base, base).replace("-", "_"))
                if base == "dask" and "distributed" in inner:
                    out.add("distributed")
        return out
    return {e: modules(e) for e in deps}


def test_every_extra_installs_what_its_commands_check():
    py = _extras_in_pyproject()
    assert set(py) == set(EXTRAS) | {"all", "dev", "run"}
    for extra, mods in EXTRAS.items():
        assert set(mods) <= py[extra], (extra, set(mods) - py[extra])
    assert py["all"] == set().union(*(py[e] for e in EXTRAS))
    assert py["all"] <= py["dev"]  # the tests need everything (make venv installs .[dev])
    assert py["run"] == py["train"] | py["plot"] | py["vqf"]  # make run: training, the figures, VQF
    core = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["dependencies"]
    assert sorted(r.split(">")[0] for r in core) == ["h5py", "numba", "numpy", "scipy"]


# ------------------------------------------------------------------------- the README's five lines

def _readme_quick_start() -> str:
    text = (ROOT / "README.md").read_text()
    section = text.split("## Five lines", 1)[1]
    return section.split("```python\n", 1)[1].split("```", 1)[0]


@pytest.mark.broad
def test_readme_quick_start_runs_the_shipped_model_without_extras():
    """The README's quick start, as written, from the repository root (its data path is relative to
    it), with every extra's package blocked: quaternions from the pretrained learned VQF on a phone
    trial. Needs the shipped model (make run, pipelines/ship_pretrained.py) and the phone data."""
    code = _readme_quick_start()
    assert len([ln for ln in code.splitlines() if ln.strip() and not ln.startswith("#")]) <= 5
    if not PRETRAINED_FILE.is_file():
        pytest.fail(f"{PRETRAINED_FILE}: no pretrained model shipped (make run, then pipelines/ship_pretrained.py)")
    if not (ROOT.parent / "shared" / "data" / "tyrex_nexus5" / "trials.json").is_file():
        pytest.skip("the phone data is not beside the repository (../shared/data/tyrex_nexus5)")
    res = _python(code + "\nimport numpy as np\nassert np.allclose(np.linalg.norm(quat, axis=1), 1.0)\n", cwd=ROOT)
    assert res.returncode == 0, res.stderr
    assert re.match(r"\(\d{4,}, 4\) \[", res.stdout)  # the printed shape: thousands of samples, 4
