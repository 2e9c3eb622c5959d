"""Loading a trained toggling filter from a model directory (``togglecf train`` output)."""
from __future__ import annotations

import hashlib
import json
from pathlib import Path

from togglecf.core.io import file_sha256
from togglecf.learn.compiled import CompiledModels
from togglecf.learn.models import load_bundle
from togglecf.toggling.gains import load_gains
from togglecf.toggling.inloop import InLoopFilter, ModelTogglingFilter, ModelVQFTogglingFilter

__all__ = ["load_toggling_filter", "load_compiled_models", "model_dir_digest", "training_trials_among"]

#: content digest of a model directory -> its CompiledModels (flattening the trees costs far more than
#: hashing the files)
_COMPILED_CACHE: dict = {}


def model_dir_digest(model_dir) -> str:
    """sha256 over ``metadata.json`` and every model file it lists: the identity of the models'
    *content*, so a directory retrained in place is never served from the cache with old trees."""
    d = Path(model_dir)
    meta_path = d / "metadata.json"
    if not meta_path.is_file():
        raise FileNotFoundError(f"{d}: no metadata.json (not a togglecf model directory, or an unfinished run)")
    raw = meta_path.read_bytes()
    h = hashlib.sha256(raw)
    for name in sorted(json.loads(raw).get("model_files", {})):
        f = d / name
        h.update(name.encode())
        h.update(f.read_bytes() if f.is_file() else b"<missing>")
    return h.hexdigest()


def load_compiled_models(model_dir) -> CompiledModels:
    """The models of a directory (schema-checked, hash-verified) flattened for the loop; cached
    per process by content (``model_dir_digest``). Read from the stored flat forest with numpy alone
    (``CompiledModels.stored``); a directory trained before that file existed is flattened from its
    XGBoost files (the ``train`` extra)."""
    key = model_dir_digest(model_dir)
    if key not in _COMPILED_CACHE:
        models = CompiledModels.stored(model_dir)
        _COMPILED_CACHE[key] = models if models is not None else CompiledModels.from_bundle(load_bundle(model_dir))
    return _COMPILED_CACHE[key]


#: learned filter kind -> the class that runs it with its models in the loop
IN_LOOP = {"toggling": ModelTogglingFilter, "vqf_toggling": ModelVQFTogglingFilter}


def load_toggling_filter(model_dir, fs: float, use_mag: bool = True, kind: str = "toggling") -> InLoopFilter:
    """A trained filter of a model directory: the models compiled for the loop, with the learned
    gains of ``kind`` (``"toggling"``: the toggling CF; ``"vqf_toggling"``: the VQF core with
    learned time constants) in 9D (``use_mag``) or 6D."""
    return IN_LOOP[kind](fs, load_gains(model_dir, use_mag=use_mag, kind=kind), models=load_compiled_models(model_dir),
                         use_mag=use_mag)


def training_trials_among(model_dir, files: dict) -> list[str]:
    """The names of ``files`` (trial name -> path) that the models of ``model_dir`` were trained
    on: a file of the same name and content (sha256) as one its metadata lists, wherever it lies,
    so that a score on them can be flagged as in-sample."""
    meta = json.loads((Path(model_dir) / "metadata.json").read_text())
    return trained_files_among(meta.get("data_files", {}), files)


def trained_files_among(data_files: dict, files: dict) -> list[str]:
    """The names of ``files`` (trial name -> path) among ``data_files`` (a model's training files:
    anything -> ``{"file": name, "sha256": ...}``), by file name and content."""
    trained = {}
    for v in data_files.values():
        trained.setdefault(Path(v["file"]).name, set()).add(v.get("sha256"))
    return [name for name, path in files.items()
            if Path(path).name in trained and Path(path).is_file() and file_sha256(path) in trained[Path(path).name]]
