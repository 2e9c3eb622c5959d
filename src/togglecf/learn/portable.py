"""A trained model in one file that numpy alone reads: the compiled forest of ``CompiledModels``, its
feature settings, training ranges and schema hash, the learned gains (settings as plain dicts, one
per mode of ``gains.json``) and free metadata (what a model card states).

The file is an uncompressed ``.npz`` (``numpy.load(path, allow_pickle=False)`` opens it) written with
fixed zip time stamps, so the same model gives the same bytes: ``make run`` can check that it
reproduces the model the package ships. Format ``PORTABLE_FORMAT``; a file of another format is
refused with what to do.
"""
from __future__ import annotations

import io
import json
import zipfile
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from togglecf.core.io import atomic_write_bytes, to_jsonable
from togglecf.features.windows import FEATURE_VERSION, FeatureSettings
from togglecf.learn.compiled import CompiledModels
from togglecf.learn.trees import FlatForest

__all__ = ["PORTABLE_FORMAT", "PortableModel", "save_portable", "load_portable"]

#: version of the file layout below
PORTABLE_FORMAT = 1
_RANGE_ARRAYS = ("feature_low", "feature_high")
_ZIP_TIME = (1980, 1, 1, 0, 0, 0)  # fixed: the same model, the same bytes


@dataclass(frozen=True)
class PortableModel:
    """What a portable file holds.

    Attributes:
        models: the compiled forest with its feature settings and ranges.
        gains: mode (``"vqf_9d"``, ``"vqf_6d"``, ...) -> the learned filter's settings as a dict
            (JSON types; lists for tuples).
        metadata: free JSON metadata (training data, rates, held-out results, licences).
    """

    models: CompiledModels
    gains: dict
    metadata: dict


def save_portable(path, models: CompiledModels, gains: dict, metadata: dict) -> Path:
    """Write ``models``, ``gains`` (mode -> settings dict) and ``metadata`` to ``path`` atomically. The header is
    strict JSON: a value that is not finite (e.g. an objective of +inf in a re-learning's report) is written as
    null (``core.io.to_jsonable``), so any JSON reader opens it."""
    f = models.forest
    header = {"format": PORTABLE_FORMAT, "feature_version": FEATURE_VERSION, "class_names": list(models.class_names),
              "feature_settings": asdict(models.feature_settings), "schema_hash": models.schema_hash,
              "max_out_of_range": models.max_out_of_range, "link": f.link, "n_features": int(f.n_features),
              "gains": gains, "metadata": metadata}
    arrays = {**f.as_arrays(), "feature_low": models.feature_low, "feature_high": models.feature_high}
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", compression=zipfile.ZIP_STORED) as z:
        z.writestr(zipfile.ZipInfo("header.json", _ZIP_TIME),
                   json.dumps(to_jsonable(header), sort_keys=True, indent=1, ensure_ascii=False,
                              allow_nan=False).encode())
        for name in sorted(arrays):
            one = io.BytesIO()
            np.lib.format.write_array(one, np.ascontiguousarray(arrays[name]), allow_pickle=False)
            z.writestr(zipfile.ZipInfo(f"{name}.npy", _ZIP_TIME), one.getvalue())
    return atomic_write_bytes(path, buf.getvalue())


def load_portable(path) -> PortableModel:
    """Read a file written by ``save_portable``; refuses another format or feature version."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such model file")
    try:
        with zipfile.ZipFile(path) as z:
            header = json.loads(z.read("header.json"))
            arrays = {n[:-4]: np.lib.format.read_array(io.BytesIO(z.read(n)), allow_pickle=False)
                      for n in z.namelist() if n.endswith(".npy")}
    except (zipfile.BadZipFile, KeyError, ValueError) as e:
        raise ValueError(f"{path}: not a togglecf model file ({e})") from None
    if header.get("format") != PORTABLE_FORMAT:
        raise ValueError(f"{path}: model file format {header.get('format')!r}, this togglecf reads format "
                         f"{PORTABLE_FORMAT}: install the togglecf version that wrote it, or retrain")
    if header.get("feature_version") != FEATURE_VERSION:
        raise ValueError(f"{path}: trained on feature schema v{header.get('feature_version')}, this togglecf "
                         f"computes v{FEATURE_VERSION}: retrain it with `togglecf train`")
    missing = [n for n in _RANGE_ARRAYS if n not in arrays]
    if missing:
        raise ValueError(f"{path}: model file without {', '.join(missing)}")
    try:
        forest = FlatForest.from_dict({**arrays, "link": header["link"], "n_features": header["n_features"]})
    except (KeyError, ValueError) as e:
        raise ValueError(f"{path}: damaged forest ({e})") from None
    models = CompiledModels(forest, header["class_names"], FeatureSettings.from_dict(header["feature_settings"]),
                            header["schema_hash"], arrays["feature_low"], arrays["feature_high"],
                            header["max_out_of_range"])
    return PortableModel(models, header["gains"], header["metadata"])
