"""Embedded export of a trained model bundle as C code.

Two formats, each checked against the Python reference before it is reported as exported:

* ``tl2cgen``: every XGBoost booster of the bundle (``classifier``, ``acc_x`` … ``mag_z``) is
  loaded into Treelite, saved as a Treelite checkpoint (``<name>.tl``) and turned into C by
  TL2cgen (if/else code, optionally with quantized thresholds). The generated code is compiled
  with gcc and its predictions are compared with XGBoost's own on every window of the given
  trials, both through ``tl2cgen.Predictor`` (the unmodified code) and through our own batch
  harness linked against the *firmware* copies (all seven models in one library).
* ``array``: the bundle's merged ``FlatForest`` (outputs: S class margins, η_a xyz, η_m xyz, as
  the in-loop filter uses it) and each booster alone as constant C arrays (8 bytes per node:
  int16 feature, float32 threshold-or-leaf-value, uint16 right-child offset; the left child is
  the next node) with a ~20-line walker ``float <prefix>predict(const float *x, float *out)``.
  Checked against ``FlatForest.predict_margin``.

TL2cgen facts this module relies on (each verified in ``tests/test_export.py``):

* the generated ``predict(union Entry *data, int pred_margin, float *result)`` ADDS the leaf
  values (and the base scores) into ``result``: the caller must zero it first;
* a feature is missing only when ``data[i].missing == -1`` (the bit pattern 0xFFFFFFFF); a NaN
  stored in ``fvalue`` counts as present and takes the ``x < thr`` = false (right) branch, which
  is not XGBoost's rule (NaN follows ``default_left``): set ``missing = -1`` for NaN features;
* every generated model defines the global symbols ``predict``, ``postprocess``,
  ``get_num_feature`` …: two models in one firmware collide. The firmware copies written here
  prefix every global symbol and macro of model ``<name>`` with ``tcf_<name>_`` (found with
  ``nm`` on the compiled object, so nothing is missed), and guard ``union Entry``.
* the TL2cgen wheel embeds Treelite 4.1.2; checkpoints from Treelite 4.8.1 load with a warning;
* with ``quantize=1`` TL2cgen 1.0.0 prints the threshold table of ``quantize.c`` with 8
  significant digits, which does not round-trip float32: margins were off by up to 0.2 on BROAD
  windows. ``export_tl2cgen`` rewrites that table with the booster's exact thresholds (checked).
  ``predict`` then also overwrites ``data[i].qvalue`` in place: refill the entries every call.

Smaller models and their held-out accuracy: ``togglecf.run.prune`` (the pruning sweep).

``measure_sizes`` compiles C files with ``gcc -Os -c`` and reads ``size`` for the host and,
when ``riscv64-unknown-elf-gcc`` is installed, for ``-march=rv32imc -mabi=ilp32`` (with
picolibc's headers when available).
"""
from __future__ import annotations

import ctypes
import json
import re
import shutil
import tempfile
from pathlib import Path

import numpy as np

from togglecf.data.broad import DatasetIndex, resolve_data_dir
from togglecf.embedded.toolchain import c_float, gcc_shared, measure_sizes, run_command
from togglecf.features.windows import FeatureSettings, trial_features
from togglecf.learn.compiled import CompiledModels
from togglecf.learn.models import load_bundle
from togglecf.learn.trees import FlatForest

__all__ = ["BOOSTER_NAMES", "export_tl2cgen", "export_tl2cgen_boosters", "export_array_c", "bundle_boosters",
           "window_features_of_trials", "tl2cgen_batch_predict", "array_batch_predict", "forest_to_c",
           "rename_tl2cgen_sources", "model_sizes", "preorder", "C_LAYOUTS", "c_layout_bytes",
           "ARRAY_HARNESS", "ARRAY_LINK_MAIN", "tl2cgen_link_main",
           "TOLERANCE"]

BOOSTER_NAMES = ("classifier", "acc_x", "acc_y", "acc_z", "mag_x", "mag_y", "mag_z")
TOLERANCE = 1e-5


# --------------------------------------------------------------------------------------- helpers

def bundle_boosters(bundle) -> dict:
    """``{name: xgboost.Booster}`` of a loaded bundle, in ``BOOSTER_NAMES`` order."""
    out = {"classifier": bundle.classifier.booster_}
    for target in ("acc", "mag"):
        for ax, b in zip("xyz", bundle.regressors[target].boosters_):
            out[f"{target}_{ax}"] = b
    return out


def window_features_of_trials(bundle, trials=None, data_dir=None) -> np.ndarray:
    """Feature rows ``(n, n_features)`` float32 of every window of ``trials`` (BROAD), computed
    with the bundle's feature settings."""
    settings = FeatureSettings.from_dict({k: v for k, v in bundle.schema.settings.items() if k != "gravity"})
    index = DatasetIndex.from_dir(resolve_data_dir(data_dir))
    rows = [trial_features(index.load(name), settings)[0] for name in index.select(trials)]
    return np.ascontiguousarray(np.vstack(rows), np.float32)


def _xgb_predict(booster, X, margin: bool) -> np.ndarray:
    import xgboost as xgb

    dm = xgb.DMatrix(np.asarray(X, np.float32), missing=np.nan, feature_names=booster.feature_names)
    p = np.asarray(booster.predict(dm, output_margin=margin), np.float64)
    return p.reshape(len(X), -1)


# ------------------------------------------------------------------------------------- tl2cgen

def _global_symbols(obj: Path) -> list:
    out = run_command(["nm", "--defined-only", "-g", obj])
    return sorted({line.split()[-1] for line in out.splitlines() if line.strip()})


def rename_tl2cgen_sources(src_dir, dst_dir, prefix: str) -> list:
    """Copy TL2cgen's generated sources from ``src_dir`` to ``dst_dir`` with every global
    symbol (and the header's ``N_TARGET``/``MAX_N_CLASS`` macros) prefixed, ``union Entry``
    guarded, and the header renamed ``<prefix>header.h``. Returns the C files written."""
    src_dir, dst_dir = Path(src_dir), Path(dst_dir)
    dst_dir.mkdir(parents=True, exist_ok=True)
    recipe = json.loads((src_dir / "recipe.json").read_text())
    sources = [src_dir / f"{s['name']}.c" for s in recipe["sources"]]
    with tempfile.TemporaryDirectory() as tmp:  # the symbols the code really defines
        symbols = set()
        for s in sources:
            obj = Path(tmp) / f"{s.stem}.o"
            run_command(["gcc", "-O0", "-c", s, "-o", obj, f"-I{src_dir}"])
            symbols.update(_global_symbols(obj))
    names = sorted(symbols | {"predict", "postprocess", "get_num_target", "get_num_class", "get_num_feature",
                              "get_threshold_type", "get_leaf_output_type"}, key=len, reverse=True)
    ident = re.compile(r"\b(" + "|".join(map(re.escape, names)) + r")\b")
    macro = re.compile(r"\b(N_TARGET|MAX_N_CLASS)\b")
    header_name = f"{prefix}header.h"

    def convert(text: str) -> str:
        text = text.replace('#include "header.h"', f'#include "{header_name}"')
        text = ident.sub(lambda m: prefix + m.group(1), text)
        return macro.sub(lambda m: prefix.upper() + m.group(1), text)

    header = convert((src_dir / "header.h").read_text())
    header = re.sub(r"(union Entry \{.*?\};)", r"#ifndef TCF_UNION_ENTRY\n#define TCF_UNION_ENTRY\n\1\n#endif",
                    header, count=1, flags=re.S)
    guard = f"{prefix.upper()}HEADER_H"
    (dst_dir / header_name).write_text(f"#ifndef {guard}\n#define {guard}\n{header}\n#endif\n")
    written = []
    for s in sources:
        dst = dst_dir / f"{prefix}{s.name}"
        dst.write_text(convert(s.read_text()))
        written.append(dst)
    return written


def _exact_quantize_thresholds(path, booster):
    """TL2cgen 1.0.0 prints the threshold table of ``quantize.c`` with 8 significant digits, which
    does not round-trip float32 (measured: margins off by up to 0.2 on BROAD windows). Rewrite the
    table with the booster's exact thresholds (per feature: sorted unique split values)."""
    path = Path(path)
    text = path.read_text()
    m = re.search(r"static const float threshold\[\] = \{(.*?)\};", text, flags=re.S)
    if m is None:
        raise RuntimeError(f"{path}: no threshold table found (TL2cgen output format changed?)")
    printed = np.array([float(v) for v in m.group(1).replace("\n", " ").split(",") if v.strip()])
    f = FlatForest.from_booster(booster)
    inner = f.feature >= 0
    exact = np.concatenate([np.unique(f.threshold[inner & (f.feature == j)]) for j in range(f.n_features)]
                           or [np.zeros(0, np.float32)])
    if len(exact) != len(printed) or not np.allclose(printed, exact, rtol=1e-6, atol=1e-30):
        raise RuntimeError(f"{path}: TL2cgen's threshold table does not match the booster's thresholds")
    table = ",\n  ".join(", ".join(c_float(v) for v in exact[i:i + 6]) for i in range(0, len(exact), 6))
    path.write_text(text[:m.start()] + f"static const float threshold[] = {{\n  {table}\n}};" + text[m.end():])


_TL_HARNESS = r"""
#include <math.h>
#include <stdlib.h>
#include <string.h>
{includes}
typedef void (*tcf_pred_fn)(union Entry *, int, float *);
/* rows X (n, nf): out (n, nout). mark_missing: NaN -> missing = -1; zero: clear result first;
   repeat: call predict that many times per row (to show that it accumulates). */
static void tcf_batch(tcf_pred_fn f, const float *X, long n, int nf, int nout, int margin, int mark_missing,
                      int zero, int repeat, float *out) {
  union Entry *e = (union Entry *)malloc(sizeof(union Entry) * (size_t)nf);
  for (long i = 0; i < n; ++i) {
    for (int j = 0; j < nf; ++j) {
      float v = X[i * nf + j];
      if (mark_missing && isnan(v)) e[j].missing = -1; else e[j].fvalue = v;
    }
    float *r = out + i * nout;
    if (zero) memset(r, 0, sizeof(float) * (size_t)nout);
    for (int k = 0; k < repeat; ++k) f(e, margin, r);
  }
  free(e);
}
{wrappers}
"""


def _tl_harness(prefixes, header_names) -> str:
    includes = "\n".join(f'#include "{h}"' for h in header_names)
    wrappers = "\n".join(
        f"void tcf_batch_{p}(const float *X, long n, int nf, int nout, int margin, int mark_missing, int zero,"
        f" int repeat, float *out) {{ tcf_batch({p}predict, X, n, nf, nout, margin, mark_missing, zero, repeat, out); }}"
        for p in prefixes)
    return _TL_HARNESS.replace("{includes}", includes).replace("{wrappers}", wrappers)


def tl2cgen_batch_predict(lib, prefix: str, X, n_out: int, margin=True, mark_missing=True, zero=True,
                          repeat=1) -> np.ndarray:
    """Predictions of the firmware copy ``prefix`` in a harness library ``lib`` (ctypes)."""
    X = np.ascontiguousarray(X, np.float32)
    out = np.zeros((X.shape[0], n_out), np.float32)
    fn = getattr(lib, f"tcf_batch_{prefix}")
    fn.restype = None
    P = ctypes.c_void_p
    fn(P(X.ctypes.data), ctypes.c_long(X.shape[0]), ctypes.c_int(X.shape[1]), ctypes.c_int(n_out),
       ctypes.c_int(int(margin)), ctypes.c_int(int(mark_missing)), ctypes.c_int(int(zero)), ctypes.c_int(repeat),
       P(out.ctypes.data))
    return out.astype(np.float64)


def _tl2cgen_predictor_predict(libpath, X, margin: bool) -> np.ndarray:
    import tl2cgen

    pred = tl2cgen.Predictor(str(libpath))
    dm = tl2cgen.DMatrix(np.asarray(X, np.float32), dtype="float32", missing=np.nan)
    return np.asarray(pred.predict(dm, pred_margin=margin), np.float64).reshape(len(X), -1)


def export_tl2cgen(model_dir, out_dir, quantize: bool = False, X=None, trials=None, data_dir=None,
                   verbose: bool = False) -> dict:
    """TL2cgen C code of every booster of ``model_dir`` in ``out_dir``, checked against XGBoost.

    ``out_dir/tl2cgen/<name>/``: TL2cgen's unmodified output (``header.h``, ``main.c``, …);
    ``out_dir/tl2cgen/<name>.tl``: the Treelite checkpoint; ``out_dir/tl2cgen/firmware/``: the
    prefixed copies (``tcf_<name>_predict`` …) that link together. Equivalence is checked on
    ``X`` (feature rows; NaN = missing) or, when ``X`` is None and ``trials`` is given, on every
    window of those trials; with neither, no check is made. Returns a report dict
    (``models``: per-model files, symbols and max abs differences; ``max_abs_diff``; ``ok``).
    """
    bundle = load_bundle(model_dir)
    if X is None and trials is not None:
        X = window_features_of_trials(bundle, trials, data_dir)
    return export_tl2cgen_boosters(bundle_boosters(bundle), out_dir, quantize=quantize, X=X, verbose=verbose)


def export_tl2cgen_boosters(boosters: dict, out_dir, quantize: bool = False, X=None, verbose: bool = False) -> dict:
    """``export_tl2cgen`` for ``{name: xgboost.Booster}`` (any gbtree boosters)."""
    import tl2cgen
    import treelite

    root = Path(out_dir) / "tl2cgen"
    fw = root / "firmware"
    root.mkdir(parents=True, exist_ok=True)
    report = {"format": "tl2cgen", "quantize": bool(quantize), "models": {}, "firmware_dir": str(fw),
              "n_rows_checked": 0 if X is None else int(len(X)), "treelite": treelite.__version__,
              "tl2cgen": tl2cgen.__version__}
    prefixes, headers, fw_sources, n_outs = [], [], [], {}
    for name, booster in boosters.items():
        model = treelite.frontend.from_xgboost(booster)
        ckpt = root / f"{name}.tl"
        model.serialize(str(ckpt))
        gen = root / name
        if gen.exists():
            shutil.rmtree(gen)
        tl2cgen.generate_c_code(model, str(gen), params={"quantize": int(bool(quantize)), "native_lib_name": name},
                                verbose=verbose)
        if quantize:
            _exact_quantize_thresholds(gen / "quantize.c", booster)
        prefix = f"tcf_{name}_"
        written = rename_tl2cgen_sources(gen, fw, prefix)
        recipe = json.loads((gen / "recipe.json").read_text())
        entry = {"checkpoint": str(ckpt), "generated": [str(gen / f"{s['name']}.c") for s in recipe["sources"]],
                 "firmware": [str(p) for p in written], "header": str(fw / f"{prefix}header.h"),
                 "predict_symbol": f"{prefix}predict", "n_trees": int(model.num_tree)}
        report["models"][name] = entry
        prefixes.append(prefix)
        headers.append(f"{prefix}header.h")
        fw_sources += written
        n_outs[name] = int(np.prod(_xgb_predict(booster, np.full((1, booster.num_features()), np.nan), True).shape))
    if X is not None:
        X = np.ascontiguousarray(X, np.float32)
        with tempfile.TemporaryDirectory() as tmp:
            harness = Path(tmp) / "harness.c"
            harness.write_text(_tl_harness(prefixes, headers))
            fwlib = ctypes.CDLL(str(gcc_shared([harness, *fw_sources], Path(tmp) / "libfw.so", [fw])))
            for (name, booster), prefix in zip(boosters.items(), prefixes):
                entry = report["models"][name]
                gen = root / name
                lib = gcc_shared(entry["generated"], Path(tmp) / f"lib{name}.so", [gen])
                ref_m = _xgb_predict(booster, X, margin=True)
                diffs = {"predictor_margin": np.abs(_tl2cgen_predictor_predict(lib, X, True) - ref_m).max(),
                         "firmware_margin": np.abs(tl2cgen_batch_predict(fwlib, prefix, X, n_outs[name]) - ref_m).max()}
                ref_p = _xgb_predict(booster, X, margin=False)
                if not np.array_equal(ref_p, ref_m):  # a link function (softmax, sigmoid)
                    diffs["predictor_proba"] = np.abs(_tl2cgen_predictor_predict(lib, X, False) - ref_p).max()
                    diffs["firmware_proba"] = np.abs(tl2cgen_batch_predict(fwlib, prefix, X, n_outs[name],
                                                                           margin=False) - ref_p).max()
                entry["max_abs_diff"] = {k: float(v) for k, v in diffs.items()}
        report["max_abs_diff"] = max(v for e in report["models"].values() for v in e["max_abs_diff"].values())
        report["ok"] = bool(report["max_abs_diff"] <= TOLERANCE)
    return report


# --------------------------------------------------------------------------------------- arrays

def preorder(forest):
    """Node order per tree with the left child right after its parent; returns (order, new_index)."""
    order = []
    new = np.full(forest.n_nodes, -1, np.int64)
    for root in forest.roots:
        stack = [int(root)]
        while stack:
            i = stack.pop()
            new[i] = len(order)
            order.append(i)
            if forest.feature[i] >= 0:
                stack.append(int(forest.right[i]))
                stack.append(int(forest.left[i]))
    return np.asarray(order, np.int64), new


def _c_array(ctype: str, name: str, values, fmt=str, per_line: int = 12) -> str:
    vals = [fmt(v) for v in values]
    lines = [", ".join(vals[i:i + per_line]) for i in range(0, len(vals), per_line)] or ["0"]
    return f"static const {ctype} {name}[{max(1, len(vals))}] = {{\n  " + ",\n  ".join(lines) + "\n};\n"


#: the C layouts of ``forest_to_c`` (the same ``predict`` API, the same margins)
C_LAYOUTS = ("array", "complete")


def _uint_type(largest: int) -> str:
    return "uint8_t" if largest <= 0xFF else ("uint16_t" if largest <= 0xFFFF else "uint32_t")


def _c_threshold(v) -> str:
    """A split threshold as a C literal: ``INFINITY`` for the complete layout's padding nodes."""
    return "INFINITY" if np.isposinf(v) else c_float(v)


def _bytes_of(ctype: str) -> int:
    return {"uint8_t": 1, "int16_t": 2, "uint16_t": 2, "uint32_t": 4, "float": 4}[ctype]


def _array_tables(forest) -> tuple:
    """The array layout: (per-node and per-tree C tables, node count, the walk's comment and code)."""
    if forest.n_features >= 0x4000:
        raise ValueError("the array format packs the feature index in 14 bits")
    order, new = preorder(forest)
    feat = forest.feature[order].astype(np.int64)
    inner = feat >= 0
    code = np.where(inner, feat | np.where(forest.default_left[order], 0x4000, 0), -1)
    thr = np.where(inner, forest.threshold[order], forest.value[order]).astype(np.float32)
    right = np.where(inner, new[np.where(inner, forest.right[order], 0)] - np.arange(len(order)), 0)
    if right.max(initial=0) > 0xFFFF:
        raise ValueError("a tree is too large for 16-bit child offsets")
    root_t = "uint16_t" if len(order) <= 0xFFFF else "uint32_t"
    tables = [("int16_t", "feat", code, str), ("float", "thr", thr, c_float), ("uint16_t", "right", right, str),
              (root_t, "root", new[forest.roots], str)]
    comment = """Node i: {P}feat[i] = feature index (bits 0-13) | 0x4000 if a missing value goes left,
   or -1 for a leaf; {P}thr[i] = split threshold, or the leaf value; the left child is
   node i + 1, the right child node i + {P}right[i]. Tree t starts at {P}root[t] and adds
   its leaf to out[{P}group[t]]."""
    walk = """  for (int t = 0; t < {U}N_TREES; ++t) {
    uint32_t i = {P}root[t];
    int16_t f;
    while ((f = {P}feat[i]) >= 0) {
      float v = x[f & 0x3FFF];
      int go_left = isnan(v) ? (f & 0x4000) != 0 : v < {P}thr[i];
      i = go_left ? i + 1u : i + {P}right[i];
    }
    acc[{P}group[t]] += {P}thr[i];
  }"""
    return tables, len(order), comment, walk


#: trees per block of the complete layout's C walk (``FlatForest.complete`` pads blocks of 8 to one depth)
_C_BLOCK = 8


def _c_level(i: str, base: str) -> str:
    """One level of the complete layout's walk in C: left (2i+1) when x < threshold, else right (2i+2)."""
    return f"{i} = 2u * {i} + 2u - (uint32_t)(xs[{{P}}feat[{base} + {i}]] < {{P}}thr[{base} + {i}]);"


def _complete_tables(forest) -> tuple:
    """The complete layout (``FlatForest.complete``): as ``_array_tables``."""
    try:
        c = forest.complete()
    except ValueError as e:  # trees too deep, or a threshold the missing-value encoding cannot take
        raise ValueError(f"the complete layout cannot hold these trees ({e}): use the array layout "
                         "(--forest-layout array)") from None
    F = forest.n_features
    tables = [(_uint_type(2 * F + 1), "feat", c.feature, str), ("float", "thr", c.threshold, _c_threshold),
              ("float", "leaf", c.value, c_float), (_uint_type(len(c.feature)), "inner", c.inner_offset, str),
              (_uint_type(len(c.value)), "leaf_at", c.leaf_offset, str), ("uint8_t", "depth", c.depth, str)]
    comment = f"""Tree t is a complete binary tree of depth {{P}}depth[t] (padded): inner node i (breadth-first:
   children 2i+1 left, 2i+2 right) at {{P}}inner[t] + i of {{P}}feat and {{P}}thr, leaf j at
   {{P}}leaf_at[t] + j of {{P}}leaf; it adds its leaf to out[{{P}}group[t]]. {{P}}feat indexes the row
   xs that holds each feature twice: j where a missing value of feature j goes left (NaN as -inf),
   {F + 1} + j where it goes right (NaN as +inf), {F} a constant 0 for padding (threshold +INFINITY:
   always left). Every step is "left when xs < threshold", without a branch on the data."""
    depth_blocks = c.depth[:len(c.depth) // _C_BLOCK * _C_BLOCK].reshape(-1, _C_BLOCK)
    if not np.all(depth_blocks == depth_blocks[:, :1]):
        raise AssertionError(f"complete(): every block of {_C_BLOCK} trees should share its padded depth")
    bases = "\n".join(f"    const uint32_t {', '.join(f'b{k} = {{P}}inner[t + {k}]' for k in range(j, j + 4))};"
                      for j in range(0, _C_BLOCK, 4))
    zeros = ", ".join(f"i{k} = 0" for k in range(_C_BLOCK))
    levels = "\n".join(f"      {_c_level(f'i{k}', f'b{k}')}" for k in range(_C_BLOCK))
    leaves = "".join(f"    acc[{{P}}group[t + {k}]] += {{P}}leaf[{{P}}leaf_at[t + {k}] + i{k} - first];\n"
                     for k in range(_C_BLOCK))
    level = _c_level("i", "b")
    walk = f"""  float xs[{2 * F + 2}];
  for (int j = 0; j < {F}; ++j) {{
    float v = x[j];
    xs[j] = isnan(v) ? -INFINITY : v;
    xs[{F + 1} + j] = isnan(v) ? INFINITY : v;
  }}
  xs[{F}] = 0.0f;
  xs[{2 * F + 1}] = 0.0f;
  int t = 0;
  for (; t + {_C_BLOCK} <= {{U}}N_TREES; t += {_C_BLOCK}) {{  /* a block of {_C_BLOCK} trees shares its padded depth */
    const uint32_t depth = {{P}}depth[t], first = (1u << depth) - 1u;
{bases}
    uint32_t {zeros};
    for (uint32_t d = 0; d < depth; ++d) {{  /* the {_C_BLOCK} walks side by side: their loads overlap */
{levels}
    }}
{leaves}  }}
  for (; t < {{U}}N_TREES; ++t) {{
    const uint32_t depth = {{P}}depth[t], b = {{P}}inner[t];
    uint32_t i = 0;
    for (uint32_t d = 0; d < depth; ++d) {level}
    acc[{{P}}group[t]] += {{P}}leaf[{{P}}leaf_at[t] + i - ((1u << depth) - 1u)];
  }}"""
    return tables, len(c.feature) + len(c.value), comment, walk


_TABLES = {"array": _array_tables, "complete": _complete_tables}


def _group_table(forest) -> tuple:
    return (_uint_type(max(forest.n_outputs - 1, 0)), "group", forest.tree_group, str)


def c_layout_bytes(forest) -> dict:
    """Constant data [bytes] of ``forest`` in each C layout of ``forest_to_c`` (its tables, the base
    margins included; None where the layout cannot hold the trees)."""
    out = {}
    for layout, tables_of in _TABLES.items():
        try:
            tables = tables_of(forest)[0]
        except ValueError:
            out[layout] = None
            continue
        tables = [*tables, _group_table(forest)]
        out[layout] = sum(_bytes_of(t) * max(1, len(v)) for t, _, v, _ in tables) + 4 * forest.n_outputs
    return out


def forest_to_c(forest, prefix: str = "tcf_", n_classes: int = 0, comment: str = "", layout: str = "array") -> tuple:
    """``(header_text, source_text)`` of a ``FlatForest`` in a C ``layout`` of ``C_LAYOUTS``: ``array``
    (compact: 8 bytes per node, a branch per node; the faster walk on a microcontroller without branch
    prediction, e.g. the Cortex-M4F of ``pipelines/bench_cycles.py``) or ``complete`` (the trees padded
    to complete binary trees, ``FlatForest.complete``: every step "left when x < threshold" without a
    branch on the data, the faster walk on a processor that predicts branches, e.g. the host of
    ``pipelines/bench_learned_vqf.py``; ``ValueError`` where it cannot hold the trees). Both define
    ``<prefix>predict`` (raw margins, the leaves summed in tree order in ``TCF_ACC_T``: the same margins)
    and, with ``n_classes``, ``<prefix>softmax``."""
    if layout not in _TABLES:
        raise ValueError(f"layout must be one of {C_LAYOUTS}, got {layout!r}")
    tables, n_nodes, node_comment, walk = _TABLES[layout](forest)
    n_out = forest.n_outputs
    P, U = prefix, prefix.upper()
    header = f"""/* {comment or 'tree ensemble'}: generated by togglecf.embedded.forest_export ({layout} layout). */
#ifndef {U}FOREST_H
#define {U}FOREST_H
#define {U}N_FEATURES {forest.n_features}
#define {U}N_OUTPUTS {n_out}
#define {U}N_CLASSES {n_classes}
#define {U}N_TREES {len(forest.roots)}
#define {U}N_NODES {n_nodes}
/* Raw margins of one feature row x[{U}N_FEATURES] (NaN = missing) into out[{U}N_OUTPUTS]
   (xgboost's rules: go left when x < threshold as float32, NaN follows the default branch).
   Returns out[0]. Do not compile with -ffast-math (it removes the isnan test). */
float {P}predict(const float *x, float *out);
""" + (f"""/* Softmax of the first {U}N_CLASSES outputs in place (class probabilities). */
void {P}softmax(float *out);
""" if n_classes else "") + "#endif\n"
    arrays = "".join(_c_array(ctype, P + name, values, fmt, 6 if ctype == "float" else 12)
                     for ctype, name, values, fmt in [*tables, _group_table(forest)])
    body = f"""/* {comment or 'tree ensemble'}: generated by togglecf.embedded.forest_export ({layout} layout).
   {node_comment.replace("{P}", P)} */
#include <math.h>
#include <stdint.h>
#include "{P}forest.h"

/* Leaf sums: double by default (matches the float64 reference to ~1e-7); -DTCF_ACC_T=float is
   smaller and faster without a double FPU, at ~1 float32 ulp of the output per ~10 trees. */
#ifndef TCF_ACC_T
#define TCF_ACC_T double
#endif

""" + arrays + _c_array("float", f"{P}base", forest.base_margin, c_float, 6) + f"""
float {P}predict(const float *x, float *out) {{
  TCF_ACC_T acc[{U}N_OUTPUTS];
  for (int k = 0; k < {U}N_OUTPUTS; ++k) acc[k] = {P}base[k];
{walk.replace("{P}", P).replace("{U}", U)}
  for (int k = 0; k < {U}N_OUTPUTS; ++k) out[k] = (float)acc[k];
  return out[0];
}}
""" + (f"""
void {P}softmax(float *out) {{
  float mx = out[0], tot = 0.0f;
  for (int k = 1; k < {U}N_CLASSES; ++k) if (out[k] > mx) mx = out[k];
  for (int k = 0; k < {U}N_CLASSES; ++k) {{ out[k] = expf(out[k] - mx); tot += out[k]; }}
  for (int k = 0; k < {U}N_CLASSES; ++k) out[k] /= tot;
}}
""" if n_classes else "")
    return header, body


ARRAY_HARNESS = r"""
#include "{P}forest.h"
void {P}batch(const float *X, long n, float *out) {
  for (long i = 0; i < n; ++i) {P}predict(X + i * {U}N_FEATURES, out + i * {U}N_OUTPUTS);
}
"""


def array_batch_predict(lib, prefix: str, X, n_out: int) -> np.ndarray:
    X = np.ascontiguousarray(X, np.float32)
    out = np.zeros((X.shape[0], n_out), np.float32)
    fn = getattr(lib, f"{prefix}batch")
    fn.restype = None
    fn(ctypes.c_void_p(X.ctypes.data), ctypes.c_long(X.shape[0]), ctypes.c_void_p(out.ctypes.data))
    return out.astype(np.float64)


def export_array_c(model_dir, out_dir, X=None, trials=None, data_dir=None, per_model: bool = True) -> dict:
    """The compact array format in ``out_dir/array/``: ``tcf_forest.{h,c}`` (the merged forest
    of ``CompiledModels``: S class margins, η_a xyz, η_m xyz) and, with ``per_model``, one
    ``tcf_<name>_forest.{h,c}`` per booster. Checked against ``FlatForest.predict_margin`` on
    ``X`` / every window of ``trials`` (as ``export_tl2cgen``). Returns a report dict."""
    bundle = load_bundle(model_dir)
    root = Path(out_dir) / "array"
    root.mkdir(parents=True, exist_ok=True)
    models = CompiledModels.from_bundle(bundle)
    forests = {"forest": (models.forest, "tcf_", len(models.class_names),
                          f"all models merged: outputs {', '.join(models.class_names)} (margins), "
                          "eta_acc xyz, eta_mag xyz")}
    if per_model:
        for name, b in bundle_boosters(bundle).items():
            forests[name] = (FlatForest.from_booster(b), f"tcf_{name}_", 0, f"booster {name} (raw margins)")
    if X is None and trials is not None:
        X = window_features_of_trials(bundle, trials, data_dir)
    report = {"format": "array", "models": {}, "n_rows_checked": 0 if X is None else int(len(X))}
    for name, (forest, prefix, n_classes, comment) in forests.items():
        h, c = forest_to_c(forest, prefix, n_classes, comment)
        (root / f"{prefix}forest.h").write_text(h)
        (root / f"{prefix}forest.c").write_text(c)
        report["models"][name] = {"source": str(root / f"{prefix}forest.c"), "header": str(root / f"{prefix}forest.h"),
                                  "predict_symbol": f"{prefix}predict", "n_nodes": int(forest.n_nodes),
                                  "n_trees": int(len(forest.roots)), "n_outputs": int(forest.n_outputs)}
    if X is not None:
        X = np.ascontiguousarray(X, np.float32)
        with tempfile.TemporaryDirectory() as tmp:
            srcs = []
            for name, (forest, prefix, _, _) in forests.items():
                hp = Path(tmp) / f"{prefix}harness.c"
                hp.write_text(ARRAY_HARNESS.replace("{P}", prefix).replace("{U}", prefix.upper()))
                srcs += [hp, root / f"{prefix}forest.c"]
            lib = ctypes.CDLL(str(gcc_shared(srcs, Path(tmp) / "libarr.so", [root])))  # all in one library
            lib_f = ctypes.CDLL(str(gcc_shared(srcs, Path(tmp) / "libarr_f.so", [root], defines=["TCF_ACC_T=float"])))
            for name, (forest, prefix, _, _) in forests.items():
                ref = forest.predict_margin(X)
                e = report["models"][name]
                e["max_abs_diff"] = float(np.abs(array_batch_predict(lib, prefix, X, forest.n_outputs) - ref).max())
                e["max_abs_diff_float_acc"] = float(np.abs(array_batch_predict(lib_f, prefix, X, forest.n_outputs)
                                                           - ref).max())
                e["max_abs_output"] = float(np.abs(ref).max())
        report["max_abs_diff"] = max(m["max_abs_diff"] for m in report["models"].values())
        report["ok"] = bool(report["max_abs_diff"] <= TOLERANCE)
    return report


# ---------------------------------------------------------------------------------------- sizes


ARRAY_LINK_MAIN = r"""
#include "tcf_forest.h"
volatile float tcf_in[TCF_N_FEATURES];
float tcf_out[TCF_N_OUTPUTS];
int main(void) {
  float x[TCF_N_FEATURES];
  for (int i = 0; i < TCF_N_FEATURES; ++i) x[i] = tcf_in[i];
  tcf_predict(x, tcf_out);
  tcf_softmax(tcf_out);
  return (int)tcf_out[0];
}
"""


def tl2cgen_link_main(prefixes, n_features: int, n_outputs: int) -> str:
    calls = "\n".join(f"  memset(r, 0, sizeof r); {p}predict(e, 0, r); s += r[0];" for p in prefixes)
    heads = "\n".join(f'#include "{p}header.h"' for p in prefixes)
    return f"""#include <string.h>
{heads}
volatile float tcf_in[{n_features}];
int main(void) {{
  union Entry e[{n_features}];
  float r[{n_outputs}], s = 0.0f;
  for (int i = 0; i < {n_features}; ++i) {{ float v = tcf_in[i]; if (v != v) e[i].missing = -1; else e[i].fvalue = v; }}
{calls}
  return (int)s;
}}
"""


def model_sizes(report, key: str, riscv: bool = True) -> dict:
    """Per model: summed sizes of its C files (``key`` = list or single path field)."""
    sizes = {}
    for name, entry in report["models"].items():
        files = entry[key] if isinstance(entry[key], list) else [entry[key]]
        per_file = measure_sizes(files, riscv=riscv)
        tot = {}
        for target in ("host", "riscv"):
            vals = [v[target] for v in per_file.values()]
            tot[target] = None if any(v is None for v in vals) else sum(v["total"] for v in vals)
        entry["size"] = tot
        if "n_nodes" in entry:
            entry["bytes_per_node_host"] = tot["host"] / entry["n_nodes"]
        sizes[name] = tot
    return sizes


# ------------------------------------------------------------------------------------------- CLI


