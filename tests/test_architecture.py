"""The package's architecture, checked: layers one way (import-linter contracts in pyproject.toml),
no module reaching into another's private names, no imports inside functions to dodge cycles,
and the default configs shipped as package data."""
import ast
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SRC = ROOT / "src" / "togglecf"


def _py_files(*dirs):
    for d in dirs:
        yield from sorted(Path(d).rglob("*.py"))


def test_import_contracts_hold():
    """`lint-imports` (import-linter) checks the layers and that the filters are ML-free."""
    exe = shutil.which("lint-imports", path=str(Path(sys.executable).parent)) or shutil.which("lint-imports")
    assert exe, "import-linter is a dev dependency: pip install -e '.[dev]'"
    res = subprocess.run([exe, "--config", str(ROOT / "pyproject.toml")], cwd=ROOT, capture_output=True, text=True)
    assert res.returncode == 0, res.stdout[-3000:] + res.stderr[-2000:]
    assert "BROKEN" not in res.stdout


#: public API of named tuples, underscored only to avoid clashing with field names
NAMEDTUPLE_API = {"_fields", "_replace", "_asdict", "_make", "_field_defaults"}


def _private_uses(path: Path) -> list[str]:
    """``from togglecf.x import _name`` and ``mod._name`` on a togglecf module bound in this file."""
    tree = ast.parse(path.read_text(), str(path))
    modules = set()  # local names bound to togglecf modules
    bad = []
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom) and node.module and node.module.startswith("togglecf"):
            for a in node.names:
                if a.name.startswith("_") and a.name != "__version__":
                    bad.append(f"{path.name}:{node.lineno} imports {node.module}.{a.name}")
                else:
                    modules.add(a.asname or a.name)
        elif isinstance(node, ast.Import):
            for a in node.names:
                if a.name.startswith("togglecf"):
                    modules.add(a.asname or a.name.split(".")[0])
    for node in ast.walk(tree):
        if (isinstance(node, ast.Attribute) and node.attr.startswith("_") and not node.attr.startswith("__")
                and node.attr not in NAMEDTUPLE_API and isinstance(node.value, ast.Name) and node.value.id in modules):
            bad.append(f"{path.name}:{node.lineno} uses {node.value.id}.{node.attr}")
    return bad


def test_no_private_cross_module_names():
    bad = [b for f in _py_files(SRC, ROOT / "pipelines") for b in _private_uses(f)]
    assert not bad, "\n".join(bad)


def test_private_name_scan_catches_a_violation(tmp_path):
    """The scan above can fail: it flags both forms it looks for."""
    f = tmp_path / "m.py"
    f.write_text("from togglecf.run.scoring import _COMPILE_FS\nfrom togglecf.run import sweep\nsweep._chunks(1, 1, 1, 1)\n")
    assert len(_private_uses(f)) == 2


#: optional or heavy third-party packages that may be imported inside a function (only where used)
LAZY_OK = {"xgboost", "dask", "distributed", "sklearn", "scipy", "h5py", "matplotlib", "pandas", "serial", "vqf",
           "treelite", "tl2cgen", "mpl_toolkits", "ctypes", "multiprocessing"}


def test_no_function_level_imports_of_togglecf():
    """Imports inside functions only for optional heavy dependencies, never of togglecf itself
    (which would hide an import cycle). One exception: the package's ``__getattr__`` (PEP 562), its
    lazy public re-exports (``togglecf.LearnedVQF``), so that ``import togglecf`` stays light; the
    package itself imports nothing of togglecf, so they cannot close a cycle."""
    bad = []
    for path in _py_files(SRC):
        tree = ast.parse(path.read_text(), str(path))
        for fn in ast.walk(tree):
            if not isinstance(fn, (ast.FunctionDef, ast.AsyncFunctionDef)):
                continue
            if path == SRC / "__init__.py" and fn.name == "__getattr__":
                continue
            for node in ast.walk(fn):
                if isinstance(node, ast.ImportFrom):
                    mod = node.module or ""
                    if node.level or mod.split(".")[0] not in LAZY_OK:
                        bad.append(f"{path.relative_to(SRC)}:{node.lineno} from {'.' * node.level}{mod} import ...")
                elif isinstance(node, ast.Import):
                    for a in node.names:
                        if a.name.split(".")[0] not in LAZY_OK:
                            bad.append(f"{path.relative_to(SRC)}:{node.lineno} import {a.name}")
    assert not bad, "\n".join(bad)


def test_default_configs_are_package_data():
    """Found inside the installed package, not through the repository's layout."""
    from togglecf.core.config import config_path
    from togglecf.run.config import DEFAULT_CONFIG, load_config
    from togglecf.run.study import DEFAULT_STUDY_CONFIG, load_study_config

    for path in (DEFAULT_CONFIG, DEFAULT_STUDY_CONFIG, config_path("default.toml")):
        assert path.is_file() and SRC in path.resolve().parents
    assert load_config()["run"]["name"] == "default"
    assert load_study_config().folds >= 2
    with pytest.raises(FileNotFoundError, match="no packaged config"):
        config_path("nope.toml")


#: the modules of ``togglecf.filters`` that may import the VQF core: the learned VQF (which runs it), the
#: package's re-exports and the filter table (which names every filter class)
VQF_CORE_IMPORTERS = {"vqf_toggling.py", "__init__.py", "catalog.py"}


def _imported_modules(path: Path) -> set:
    tree = ast.parse(path.read_text(), str(path))
    out = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom) and node.module:
            out.add(node.module)
        elif isinstance(node, ast.Import):
            out.update(a.name for a in node.names)
    return out


def test_no_filter_depends_on_the_vqf_core_but_the_learned_vqf():
    """Shared helpers (time-constant gains, quaternion load/store) live in ``filters.base`` and
    ``filters.timeconst``: no other filter imports the 700-line VQF core for them."""
    importers = {p.name for p in (SRC / "filters").glob("*.py")
                 if "togglecf.filters.vqf_core" in _imported_modules(p)}
    assert importers <= VQF_CORE_IMPORTERS, sorted(importers - VQF_CORE_IMPORTERS)
    assert "vqf_toggling.py" in importers  # the rule reads real imports (it would pass on an empty scan)
