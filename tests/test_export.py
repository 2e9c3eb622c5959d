"""Embedded export (``togglecf.embedded.forest_export``): TL2cgen C code and the compact array format predict
what XGBoost / ``FlatForest`` predict (NaN features included), the TL2cgen facts the export
relies on hold, prefixed models link together, and object sizes are measured."""
import ctypes
import shutil
import subprocess

import numpy as np
import pytest

pytest.importorskip("treelite", reason="treelite is not installed")
pytest.importorskip("tl2cgen", reason="tl2cgen is not installed")
if shutil.which("gcc") is None or shutil.which("nm") is None or shutil.which("size") is None:
    pytest.skip("gcc/binutils not installed: the exported C code cannot be compiled", allow_module_level=True)

import xgboost as xgb  # noqa: E402

from togglecf.cli.export import add_export_parser  # noqa: E402
from togglecf.embedded import forest_export as export  # noqa: E402
from togglecf.embedded import toolchain  # noqa: E402
from togglecf.learn.trees import COMPLETE_MAX_DEPTH, FlatForest  # noqa: E402

TOL = 1e-5


# ----------------------------------------------------------------------------- synthetic boosters

@pytest.fixture(scope="module")
def synthetic():
    """Two boosters trained WITH missing values (so some nodes send NaN left, which models
    trained on complete BROAD features never do): a 3-class softprob and a regressor."""
    rng = np.random.default_rng(0)
    X = rng.standard_normal((600, 6)).astype(np.float32)
    X[rng.random(X.shape) < 0.25] = np.nan
    score = np.nan_to_num(X[:, 0], nan=2.0) + 0.5 * np.nan_to_num(X[:, 1], nan=-1.5)
    y_cls = np.digitize(score, [-0.5, 0.7])
    y_reg = 3.0 * score + np.isnan(X[:, 2]) * 5.0
    common = {"tree_method": "hist", "max_depth": 4, "eta": 0.3, "nthread": 1, "seed": 0}
    clf = xgb.train({**common, "objective": "multi:softprob", "num_class": 3}, xgb.DMatrix(X, y_cls), 12)
    reg = xgb.train({**common, "objective": "reg:squarederror", "base_score": 0.0}, xgb.DMatrix(X, y_reg), 12)
    Xt = rng.standard_normal((400, 6)).astype(np.float32)
    Xt[rng.random(Xt.shape) < 0.3] = np.nan
    Xt[0] = np.nan  # an all-missing row
    # rows on the split thresholds and one float32 ulp either side (where rounding errors show)
    f = FlatForest.from_booster(reg)
    thr = f.threshold[f.feature >= 0]
    feat = f.feature[f.feature >= 0]
    edge = np.tile(Xt[1:2], (3 * len(thr), 1))
    for i, (j, t) in enumerate(zip(feat, thr)):
        for k, v in enumerate((np.nextafter(t, np.float32(-np.inf)), t, np.nextafter(t, np.float32(np.inf)))):
            edge[3 * i + k, j] = v
    return {"classifier": clf, "acc_x": reg}, np.vstack([Xt, edge])


@pytest.fixture(scope="module")
def synthetic_export(synthetic, tmp_path_factory):
    boosters, Xt = synthetic
    out = tmp_path_factory.mktemp("tl_synth")
    return export.export_tl2cgen_boosters(boosters, out, X=Xt), out


@pytest.fixture(scope="module")
def firmware_lib(synthetic_export, tmp_path_factory):
    """The prefixed firmware copies of both synthetic models + the batch harness in one library."""
    rep, _ = synthetic_export
    fw = rep["firmware_dir"]
    names = list(rep["models"])
    tmp = tmp_path_factory.mktemp("fwlib")
    h = tmp / "harness.c"
    h.write_text(export._tl_harness([f"tcf_{n}_" for n in names], [f"tcf_{n}_header.h" for n in names]))
    srcs = [h] + [f for n in names for f in rep["models"][n]["firmware"]]
    lib = toolchain.gcc_shared(srcs, tmp / "libfw.so", [fw])
    return ctypes.CDLL(str(lib)), lib


def test_synthetic_models_have_default_left_nodes(synthetic):
    boosters, _ = synthetic
    assert FlatForest.from_booster(boosters["classifier"]).default_left[
        FlatForest.from_booster(boosters["classifier"]).feature >= 0].any()


def test_tl2cgen_equals_xgboost_with_nan(synthetic_export):
    rep, out = synthetic_export
    assert rep["ok"], rep
    assert rep["max_abs_diff"] <= TOL
    for name, e in rep["models"].items():
        assert set(e["max_abs_diff"]) >= {"predictor_margin", "firmware_margin"}
        assert (out / "tl2cgen" / f"{name}.tl").is_file()
    assert "predictor_proba" in rep["models"]["classifier"]["max_abs_diff"]


def test_treelite_checkpoint_round_trips(synthetic_export, synthetic):
    import treelite

    rep, out = synthetic_export
    boosters, Xt = synthetic
    model = treelite.Model.deserialize(str(out / "tl2cgen" / "acc_x.tl"))
    assert model.num_tree == 12
    got = np.asarray(treelite.gtil.predict(model, Xt, pred_margin=True), np.float64).reshape(len(Xt), -1)
    ref = export._xgb_predict(boosters["acc_x"], Xt, margin=True)
    assert np.abs(got - ref).max() <= TOL


def test_tl2cgen_predict_accumulates_into_result(firmware_lib, synthetic):
    lib, _ = firmware_lib
    _, Xt = synthetic
    once = export.tl2cgen_batch_predict(lib, "tcf_classifier_", Xt, 3, zero=True, repeat=1)
    twice = export.tl2cgen_batch_predict(lib, "tcf_classifier_", Xt, 3, zero=True, repeat=2)
    np.testing.assert_allclose(twice, 2 * once, rtol=1e-6, atol=1e-6)  # ADDS: result must be zeroed first
    assert np.abs(once).max() > 0.1


def test_tl2cgen_nan_counts_as_present_unless_marked_missing(firmware_lib, synthetic):
    lib, _ = firmware_lib
    boosters, Xt = synthetic
    ref = export._xgb_predict(boosters["acc_x"], Xt, margin=True)
    marked = export.tl2cgen_batch_predict(lib, "tcf_acc_x_", Xt, 1, mark_missing=True)
    raw_nan = export.tl2cgen_batch_predict(lib, "tcf_acc_x_", Xt, 1, mark_missing=False)
    assert np.abs(marked - ref).max() <= TOL
    assert np.abs(raw_nan - ref).max() > 0.1  # NaN in fvalue: x < thr is false -> right, not default_left


def test_symbol_rename_links_two_models(synthetic_export, firmware_lib, tmp_path):
    rep, _ = synthetic_export
    _, libpath = firmware_lib
    syms = subprocess.run(["nm", "-D", "--defined-only", str(libpath)], capture_output=True, text=True).stdout.split()
    assert "tcf_classifier_predict" in syms and "tcf_acc_x_predict" in syms
    assert "predict" not in syms and "postprocess" not in syms
    # the unmodified TL2cgen outputs of two models do collide
    gen = [rep["models"][n]["generated"][0] for n in ("classifier", "acc_x")]
    objs = []
    for i, src in enumerate(gen):
        o = tmp_path / f"m{i}.o"
        subprocess.run(["gcc", "-O0", "-fPIC", "-c", src, "-o", str(o), f"-I{src.rsplit('/', 1)[0]}"], check=True)
        objs.append(str(o))
    res = subprocess.run(["gcc", "-shared", "-o", str(tmp_path / "clash.so"), *objs], capture_output=True, text=True)
    assert res.returncode != 0 and "multiple definition" in res.stderr


def test_firmware_headers_can_be_included_together(synthetic_export, tmp_path):
    rep, _ = synthetic_export
    c = tmp_path / "both.c"
    c.write_text('#include "tcf_classifier_header.h"\n#include "tcf_acc_x_header.h"\n'
                 "int n(void) { return tcf_classifier_get_num_feature() + tcf_acc_x_get_num_feature(); }\n")
    subprocess.run(["gcc", "-Wall", "-Werror", "-c", str(c), "-o", str(tmp_path / "both.o"),
                    f"-I{rep['firmware_dir']}"], check=True)


def test_tl2cgen_quantized_equals_xgboost(synthetic, tmp_path):
    boosters, Xt = synthetic
    rep = export.export_tl2cgen_boosters({"acc_x": boosters["acc_x"]}, tmp_path, quantize=True, X=Xt)
    assert rep["ok"], rep


@pytest.mark.parametrize("layout", export.C_LAYOUTS)
def test_array_format_equals_flatforest_and_xgboost(synthetic, tmp_path, layout):
    """Each C layout gives XGBoost's margins, missing values (NaN) included (the synthetic rows hold
    some); TOL: float32 leaves summed in double (or float) against XGBoost's float32 sums."""
    boosters, Xt = synthetic
    assert np.isnan(Xt).any(), "the rows should exercise the missing-value branches"
    for name, b in boosters.items():
        forest = FlatForest.from_booster(b)
        prefix = f"tcf_{name}_"
        h, c = export.forest_to_c(forest, prefix, n_classes=3 if name == "classifier" else 0, layout=layout)
        assert f"({layout} layout)" in h
        (tmp_path / f"{prefix}forest.h").write_text(h)
        (tmp_path / f"{prefix}forest.c").write_text(c)
        harness = tmp_path / f"{prefix}harness.c"
        harness.write_text(export.ARRAY_HARNESS.replace("{P}", prefix).replace("{U}", prefix.upper()))
        for acc in ("double", "float"):
            lib = ctypes.CDLL(str(toolchain.gcc_shared([harness, tmp_path / f"{prefix}forest.c"],
                                                     tmp_path / f"lib{name}_{acc}.so", [tmp_path],
                                                     defines=[f"TCF_ACC_T={acc}"])))
            got = export.array_batch_predict(lib, prefix, Xt, forest.n_outputs)
            assert np.abs(got - forest.predict_margin(Xt)).max() <= TOL
            assert np.abs(got - export._xgb_predict(b, Xt, margin=True)).max() <= TOL
    assert len(h) > 0


def _chain_forest(depth: int) -> FlatForest:
    """One tree whose every split sends the right branch to a leaf: ``depth`` levels, 2 depth + 1 nodes."""
    n = 2 * depth + 1
    feature = np.full(n, -1, np.int32)
    left, right = np.full(n, -1, np.int32), np.full(n, -1, np.int32)
    for d in range(depth):  # node 2d splits: left to the next split (2d + 2), right to a leaf (2d + 1)
        feature[2 * d], left[2 * d], right[2 * d] = 0, 2 * d + 2, 2 * d + 1
    value = np.arange(n, dtype=np.float32)
    threshold = np.where(feature >= 0, -np.arange(n, dtype=np.float32), 0).astype(np.float32)
    return FlatForest(feature, threshold.astype(np.float32), left, right, np.zeros(n, bool), value,
                      np.zeros(1, np.int32), np.zeros(1, np.int32), np.zeros(1), "identity", 1)


def test_layout_bytes_count_the_complete_layouts_padding():
    """``c_layout_bytes``: a chain of 10 splits (21 nodes, 8 bytes each in the array layout) pads to 1023
    inner nodes (1 + 4 bytes) and 1024 leaves (4 bytes) in the complete layout; a stump (one split,
    two leaves: 3 x 8 bytes) takes 5 + 8 there. Trees deeper than ``COMPLETE_MAX_DEPTH``: no complete
    layout, and ``forest_to_c`` says so."""
    tables = 2 + 1 + 4  # per tree: array root (uint16) + group (uint8); + the base margin (float)
    assert export.c_layout_bytes(_chain_forest(10)) == {"array": 21 * 8 + tables,
                                                        "complete": 1023 * 5 + 1024 * 4 + 2 + 2 + 1 + 1 + 4}
    assert export.c_layout_bytes(_chain_forest(1)) == {"array": 3 * 8 + tables, "complete": 5 + 8 + 1 + 1 + 1 + 1 + 4}
    deep = _chain_forest(COMPLETE_MAX_DEPTH + 1)
    assert export.c_layout_bytes(deep)["complete"] is None
    with pytest.raises(ValueError, match=r"complete layout cannot hold these trees .*deeper.*--forest-layout array"):
        export.forest_to_c(deep, layout="complete")
    with pytest.raises(ValueError, match="layout must be one of"):
        export.forest_to_c(deep, layout="tree")


def test_complete_layout_walks_the_chain_like_the_forest(tmp_path):
    """The chain's leaves are reached at every depth, padding included (a leaf above the padded depth
    continues left): the C margins equal ``predict_margin`` on values either side of every threshold
    (node 2d splits at -2d), on them, and on NaN (default right)."""
    chain = _chain_forest(6)
    h, c = export.forest_to_c(chain, "tcf_", layout="complete")
    (tmp_path / "tcf_forest.h").write_text(h)
    (tmp_path / "tcf_forest.c").write_text(c)
    harness = tmp_path / "harness.c"
    harness.write_text(export.ARRAY_HARNESS.replace("{P}", "tcf_").replace("{U}", "TCF_"))
    lib = ctypes.CDLL(str(toolchain.gcc_shared([harness, tmp_path / "tcf_forest.c"], tmp_path / "lib.so",
                                               [tmp_path])))
    X = np.array([[v] for v in (0.5, 0.0, -1.0, -2.0, -3.0, -4.0, -5.0, -7.0, -9.0, -10.0, -11.0, np.nan)], np.float32)
    want = chain.predict_margin(X)
    assert len(np.unique(want)) == 7, "the rows should end in every leaf"
    assert np.array_equal(export.array_batch_predict(lib, "tcf_", X, 1), want)


def test_measure_sizes_host_and_riscv(tmp_path):
    c = tmp_path / "f.c"
    c.write_text("static const float t[256] = {1.0f};\nfloat f(int i) { return t[i & 255]; }\n")
    sizes = toolchain.measure_sizes([c])[str(c)]
    assert sizes["host"]["total"] >= 1024 and sizes["host"]["text"] > 0
    if shutil.which(toolchain.RISCV_GCC):
        assert sizes["riscv"]["total"] >= 1024
    else:
        assert sizes["riscv"] is None


# ------------------------------------------- a model trained on real data (the shipped mini BROAD cuts)

@pytest.fixture(scope="module")
def tiny_models(tiny_model_dir):
    return tiny_model_dir


@pytest.fixture(scope="module")
def real_X(tiny_models, mini_index):
    from togglecf.learn.models import load_bundle

    # every window of the 3 mini trials (408 rows): the training trials themselves, which does not
    # matter here (the claim is that the exported code predicts what the booster predicts on the
    # features of real recordings, not how well; both get the same float32 features). It used the
    # unseen full trial 05 (2040 rows) when the tiny models were trained on the full BROAD trials.
    X = export.window_features_of_trials(load_bundle(tiny_models), None, mini_index.root)
    rng = np.random.default_rng(1)
    Xn = X[:300].copy()
    Xn[rng.random(Xn.shape) < 0.2] = np.nan  # non-finite samples make NaN features in the filter
    return np.vstack([X, Xn])


def test_real_bundle_tl2cgen_equals_xgboost(tiny_models, real_X, tmp_path):
    rep = export.export_tl2cgen(tiny_models, tmp_path, X=real_X)
    assert rep["ok"], rep
    assert set(rep["models"]) == set(export.BOOSTER_NAMES)


def test_real_bundle_array_equals_flatforest(tiny_models, real_X, tmp_path):
    rep = export.export_array_c(tiny_models, tmp_path, X=real_X)
    assert rep["ok"], rep
    assert set(rep["models"]) == {"forest", *export.BOOSTER_NAMES}
    sizes = export.model_sizes(rep, "source", riscv=False)
    n = rep["models"]["forest"]["n_nodes"]
    assert 8 * n <= sizes["forest"]["host"] <= 8 * n + 2048  # 8 bytes per node + walker and tables


def test_cli_export(tiny_models, mini_index, tmp_path, capsys):
    import argparse

    p = argparse.ArgumentParser()
    add_export_parser(p.add_subparsers(dest="command"))
    args = p.parse_args(["export", "--models", str(tiny_models), "--out", str(tmp_path / "emb"), "--format", "array",
                         "--data", str(mini_index.root), "--trials", "24", "--no-riscv"])
    assert args.func(args) == 0
    out = capsys.readouterr().out
    assert "OK" in out and "forest" in out
    assert (tmp_path / "emb" / "export_report.json").is_file()
    assert (tmp_path / "emb" / "array" / "tcf_forest.c").is_file()


def test_cli_forest_layout_choices_are_the_exports():
    """``--forest-layout`` lists its choices literally (the CLI parser stays light): they must be
    ``forest_export.C_LAYOUTS``, array the default."""
    import argparse

    p = argparse.ArgumentParser()
    add_export_parser(p.add_subparsers(dest="command"))
    assert p.parse_args(["export", "--out", "x"]).forest_layout == "array"
    for layout in export.C_LAYOUTS:
        assert p.parse_args(["export", "--out", "x", "--forest-layout", layout]).forest_layout == layout
    with pytest.raises(SystemExit):
        p.parse_args(["export", "--out", "x", "--forest-layout", "tree"])


def test_c_float_literals_round_trip():
    for v in (0.0, -10.0, 1e-5, 1.5, -0.0, 3e38, 1e-45, 0.1):
        lit = toolchain.c_float(v)
        assert lit.endswith("f") and any(c in lit for c in ".e")
        assert np.float32(float(lit[:-1])) == np.float32(v)


@pytest.mark.skipif(shutil.which(toolchain.RISCV_GCC) is None, reason="riscv64-unknown-elf-gcc not installed")
def test_linked_riscv_program(synthetic, tmp_path):
    boosters, _ = synthetic
    h, c = export.forest_to_c(FlatForest.from_booster(boosters["classifier"]), "tcf_", n_classes=3)
    (tmp_path / "tcf_forest.h").write_text(h)
    (tmp_path / "tcf_forest.c").write_text(c)
    size = toolchain.link_riscv([tmp_path / "tcf_forest.c"], [tmp_path], export.ARRAY_LINK_MAIN)
    if size is None:
        pytest.skip("picolibc for riscv64-unknown-elf not installed")
    assert size["flash"] > 8 * FlatForest.from_booster(boosters["classifier"]).n_nodes


@pytest.mark.skipif(shutil.which(toolchain.RISCV_GCC) is None, reason="riscv64-unknown-elf-gcc not installed")
def test_linked_riscv_tl2cgen_models_together(synthetic_export):
    rep, _ = synthetic_export
    files = [f for e in rep["models"].values() for f in e["firmware"]]
    size = toolchain.link_riscv(files, [rep["firmware_dir"]],
                             export.tl2cgen_link_main([f"tcf_{n}_" for n in rep["models"]], 6, 3))
    if size is None:
        pytest.skip("picolibc for riscv64-unknown-elf not installed")
    assert size["flash"] > 1000


@pytest.mark.skipif(shutil.which(toolchain.RISCV_GCC) is None, reason="riscv64-unknown-elf-gcc not installed")
def test_stack_usage_of_the_array_walker(synthetic, tmp_path):
    """gcc's -fstack-usage figure for tcf_predict: the walker keeps one accumulator per output
    (double by default) on the stack, so more outputs need more stack, and never less than that."""
    boosters, _ = synthetic
    forest = FlatForest.from_booster(boosters["classifier"])
    h, c = export.forest_to_c(forest, "tcf_", n_classes=3)
    (tmp_path / "tcf_forest.h").write_text(h)
    (tmp_path / "tcf_forest.c").write_text(c)
    stack = toolchain.stack_usage(tmp_path / "tcf_forest.c", [tmp_path], "tcf_predict")
    assert 8 * forest.n_outputs <= stack < 1024
    with pytest.raises(RuntimeError, match="no stack-usage entry"):
        toolchain.stack_usage(tmp_path / "tcf_forest.c", [tmp_path], "no_such_function")


@pytest.mark.parametrize("use_mag", [True, False], ids=["9D", "6D"])
def test_export_without_models_writes_the_pretrained_learned_vqf(use_mag, mini_trial, tmp_path, capsys):
    """``export --filter vqf_toggling`` with no ``--models``: the shipped portable model as the C filter,
    which computes what ``LearnedVQF`` computes. Where the shipped settings learn nothing
    (``learning_off``) both run the core alone (``TCF_LEARNING_OFF 1``: no trees walked, no prediction
    held) and the C is float32 against float64 arithmetic only; else the C driven by the Python
    filter's own predictions is. Either within the bound the model-directory export is held to on the
    same cut (``test_cvqf_toggling.ARITH_TOL["mini"]``, 0.001°)."""
    import json

    from togglecf.cli.main import main
    from togglecf.core.io import file_sha256
    from togglecf.embedded import cvqf_toggling as cv
    from togglecf.core.quaternion import angle_between
    from togglecf.toggling.pretrained import PRETRAINED_FILE, LearnedVQF

    if not PRETRAINED_FILE.is_file():
        pytest.skip("this checkout ships no pretrained model")
    out = tmp_path / "emb"
    mode = [] if use_mag else ["--6d"]
    assert main(["export", "--filter", "vqf_toggling", "--no-riscv", "--out", str(out), *mode]) == 0
    report = json.loads((out / "export_report.json").read_text())
    assert report["source"] == str(PRETRAINED_FILE) and set(report) == {"source", "filter"}  # no XGBoost trees
    config = (out / "filter" / "tcf_config.h").read_text()
    assert file_sha256(PRETRAINED_FILE)[:12] in config  # names its model
    t = mini_trial
    mag = t.mag if use_mag else None
    f = LearnedVQF(t.fs, use_mag=use_mag)
    py = f.update_batch(t.gyr, t.acc, mag)
    assert f"#define TCF_LEARNING_OFF {int(f.runs_core_alone)}" in config
    exe = cv.build_vqft_harness(out / "filter")
    if f.runs_core_alone:
        qc, diag = cv.run_vqft_harness(exe, t.gyr, t.acc, mag, diagnostics=True, fs=t.fs)
        assert np.isnan(diag[f"p_{report['filter']['class_names'][0]}"]).all()  # the trees never ran
    else:
        names = [f"p_{c}" for c in report["filter"]["class_names"]] + [
            f"eta_{k}_{ax}" for k in ("acc", "mag") for ax in "xyz"]
        P = np.stack([py.diagnostics[k] for k in names], axis=1)
        qc = cv.run_vqft_harness(exe, t.gyr, t.acc, mag, predictions=P, fs=t.fs)
    assert np.degrees(angle_between(qc, py.quat)).max() <= 0.001


def test_export_refuses_a_portable_file_for_the_toggling_cf(tmp_path, capsys):
    from togglecf.cli.main import main

    assert main(["export", "--out", str(tmp_path / "a")]) == 1  # --filter toggling needs a model directory
    assert "--models DIR is required" in capsys.readouterr().err
    assert main(["export", "--models", "x.npz", "--out", str(tmp_path / "b")]) == 1
    err = capsys.readouterr().err
    assert "export it with --filter vqf_toggling" in err and "Traceback" not in err
