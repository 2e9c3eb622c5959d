"""Measurements of a forest as deployed: object sizes (array and TL2cgen formats), rv32 stack and
host time per prediction, and which boosters and features the filter's trees use."""
from __future__ import annotations

import ctypes
import tempfile
import time
from pathlib import Path

import numpy as np

from togglecf.embedded.forest_export import (
    ARRAY_HARNESS,
    BOOSTER_NAMES,
    array_batch_predict,
    export_tl2cgen_boosters,
    forest_to_c,
    model_sizes,
    preorder,
)
from togglecf.embedded.toolchain import gcc_shared, measure_sizes, native_stderr_silenced, stack_usage
from togglecf.filters.prediction import PredictionLayout

__all__ = ["used_boosters", "array_measurements", "tl2cgen_sizes", "used_features"]


def used_boosters(forest, n_classes: int) -> list:
    """Booster names whose trees the filter's ``forest`` holds (unused outputs are dropped)."""
    groups = set(np.unique(forest.tree_group).tolist())
    layout = PredictionLayout.of(n_classes)  # the forest's outputs are a prediction row: η̂_a xyz, η̂_m xyz after the classes
    return ["classifier"] + [n for i, n in zip(layout.outputs(layout.eta), BOOSTER_NAMES[1:]) if i in groups]


def array_measurements(forest, n_classes: int, X_test, riscv: bool) -> dict:
    """Object sizes, rv32 stack and host time per prediction of ``forest`` in the array format."""
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        h, c = forest_to_c(forest, "tcf_", n_classes)
        (tmp / "tcf_forest.h").write_text(h)
        src = tmp / "tcf_forest.c"
        src.write_text(c)
        size = measure_sizes([src], riscv=riscv)[str(src)]
        stack = stack_usage(src, [tmp], "tcf_predict") if riscv else None
        harness = tmp / "harness.c"
        harness.write_text(ARRAY_HARNESS.replace("{P}", "tcf_").replace("{U}", "TCF_"))
        lib = ctypes.CDLL(str(gcc_shared([harness, src], tmp / "libf.so", [tmp], opt="-O2")))
        X = np.ascontiguousarray(X_test, np.float32)
        array_batch_predict(lib, "tcf_", X[:100], forest.n_outputs)  # warm-up
        t0 = time.perf_counter()
        array_batch_predict(lib, "tcf_", X, forest.n_outputs)
        us = 1e6 * (time.perf_counter() - t0) / max(1, len(X))
    io_bytes = 4 * (forest.n_features + forest.n_outputs)
    return {"array_host_bytes": size["host"]["total"],
            "array_riscv_bytes": None if size["riscv"] is None else size["riscv"]["total"],
            "ram_bytes": None if stack is None else stack + io_bytes, "us_per_prediction": us}


def tl2cgen_sizes(boosters: dict, riscv: bool) -> dict:
    out = {}
    for quantize, tag in ((False, "tl2cgen"), (True, "tl2cgen_q")):
        with tempfile.TemporaryDirectory() as tmp, native_stderr_silenced():  # Treelite's version notes, x100
            rep = export_tl2cgen_boosters(boosters, tmp, quantize=quantize)
            sizes = model_sizes(rep, "firmware", riscv=riscv)
        for target in ("host", "riscv"):
            vals = [s[target] for s in sizes.values()]
            out[f"{tag}_{target}_bytes"] = None if any(v is None for v in vals) else int(sum(vals))
    return out


def used_features(forest) -> int:
    """Distinct features the forest's trees split on (only trees still walked: ``without_outputs``
    keeps the dropped trees' nodes in the arrays)."""
    feat = forest.feature[preorder(forest)[0]]
    return int(np.unique(feat[feat >= 0]).size)
