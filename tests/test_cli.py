"""The `togglecf` command line on real and on synthetic data."""
import json
import os
import re
import sys
import warnings

import pandas as pd
import pytest

from conftest import TINY_TRAIN_TOML
from test_data import make_broad_dir, synthetic_fields, write_hdf5
from togglecf.cli.library_noise import library_noise_filtered
from togglecf.cli.main import main


def test_evaluate_on_synthetic_dir_writes_tables(tmp_path, capsys):
    data = make_broad_dir(tmp_path / "b", ["01_a", "02_b"], ["01_a", "02_b", "03_c"])
    out = tmp_path / "report"
    assert main(["evaluate", "--filter", "cf", "--param", "tau=0.3482", "--data", str(data), "--out", str(out),
                 "--jobs", "1"]) == 0
    captured = capsys.readouterr()
    assert "01_a" in captured.out and "per BROAD group" in captured.out
    assert "missing (1): 03_c" in captured.err
    per_trial = pd.read_csv(out / "per_trial.csv", index_col=0)
    assert list(per_trial.index) == ["01_a", "02_b"]
    assert {"total", "heading", "inclination", "roll", "pitch", "yaw", "us_per_sample"} <= set(per_trial.columns)
    res = json.loads((out / "results.json").read_text())
    assert res["params"] == {"tau": 0.3482} and res["missing_trials"] == ["03_c"]
    assert pd.read_csv(out / "per_group.csv", index_col=0).loc["all_trials", "n_trials"] == 2


def test_evaluate_several_filters_in_one_table(tmp_path, capsys):
    """``--filters``: one table, a row per filter, and each filter's files under --out as --filter writes them."""
    pytest.importorskip("vqf")
    data = make_broad_dir(tmp_path / "b", ["01_a", "02_b"], ["01_a", "02_b"])
    out = tmp_path / "report"
    assert main(["evaluate", "--filters", "cf,vqf,madgwick", "--data", str(data), "--out", str(out),
                 "--jobs", "1"]) == 0
    printed = capsys.readouterr().out
    lines = printed.splitlines()
    rows = lines[lines.index(next(ln for ln in lines if ln.split() == ["filter"])) + 1:]
    assert [ln.split()[0] for ln in rows] == ["cf", "vqf", "madgwick"]  # one table, the filters in order
    assert "per trial" not in printed  # not three single-filter reports
    summary = pd.read_csv(out / "summary.csv", index_col=0)
    assert list(summary.index) == ["cf", "vqf", "madgwick"]
    assert {"n_trials", "total", "heading", "inclination", "us_per_sample", "all_trials", "g1"} <= set(summary.columns)
    for name in summary.index:
        per_trial = pd.read_csv(out / name / "per_trial.csv", index_col=0)
        assert list(per_trial.index) == ["01_a", "02_b"]
        assert summary.loc[name, "total"] == pytest.approx(per_trial["total"].mean(), abs=1e-6)
        assert summary.loc[name, "g1"] == pytest.approx(per_trial.loc["01_a", "total"], abs=1e-6)  # g1: 01_a only
        assert json.loads((out / name / "results.json").read_text())["filter"] == name
    assert summary.loc["vqf", "total"] != summary.loc["madgwick", "total"]
    # the same filter alone gives the same numbers
    assert main(["evaluate", "--filter", "madgwick", "--data", str(data), "--out", str(tmp_path / "one"),
                 "--jobs", "1"]) == 0
    one = pd.read_csv(tmp_path / "one" / "per_trial.csv", index_col=0)
    assert one["total"].mean() == pytest.approx(summary.loc["madgwick", "total"], abs=1e-6)


@pytest.mark.parametrize("argv,message", [
    (["--filters", "cf,nope"], "unknown filter 'nope' in --filters"),
    (["--filters", "cf,cf"], "--filters names cf twice"),
    (["--filters", "cf,toggling"], "--filters toggling needs --models DIR"),
    (["--filters", "cf,madgwick", "--models", "m"], "--models DIR is for toggling / vqf_toggling"),
    (["--filters", "cf,madgwick", "--param", "tau=0.3"], "--param sets one filter's settings"),
    (["--filters", "learned_vqf", "--models", "m"], "--models DIR is for toggling / vqf_toggling"),
])
def test_evaluate_filters_refusals_are_one_line(argv, message, tmp_path, capsys):
    data = make_broad_dir(tmp_path / "b", ["01_a"], ["01_a"])
    assert main(["evaluate", *argv, "--data", str(data), "--jobs", "1"]) == 1
    err = capsys.readouterr().err
    assert message in err and "Traceback" not in err
    assert err.strip().splitlines()[-1].startswith("togglecf evaluate: error: ")


def test_evaluate_filter_and_filters_are_exclusive(capsys):
    with pytest.raises(SystemExit):
        main(["evaluate", "--filter", "cf", "--filters", "cf,madgwick"])
    assert "not allowed with argument" in capsys.readouterr().err


def test_errors_are_one_clear_line(tmp_path, capsys):
    assert main(["evaluate", "--filter", "cf", "--data", str(tmp_path)]) == 1
    err = capsys.readouterr().err
    assert "no BROAD data in" in err and "togglecf download" in err and "Traceback" not in err
    data = make_broad_dir(tmp_path / "b", ["01_a"], ["01_a"])
    assert main(["evaluate", "--filter", "cf", "--param", "tau=nan", "--data", str(data)]) == 1
    assert "CFSettings.tau must be finite" in capsys.readouterr().err
    assert main(["evaluate", "--filter", "cf", "--trials", "09", "--data", str(data)]) == 1
    assert "not listed" in capsys.readouterr().err


def _bad_dir(tmp_path):
    """01_a fine but for a NaN burst (5 %), 02_b too short (10 samples), 03_c 20 % NaN in acc."""
    names = ["01_a", "02_b", "03_c"]
    data = make_broad_dir(tmp_path / "b", [], names)
    f = synthetic_fields(600, seed=1)
    f["imu_acc"][300:330] = float("nan")
    write_hdf5(data / "01_a.hdf5", f)
    write_hdf5(data / "02_b.hdf5", {k: v[:10] for k, v in synthetic_fields(600, seed=2).items()})
    f = synthetic_fields(600, seed=3)
    f["imu_acc"][100:220] = float("nan")
    write_hdf5(data / "03_c.hdf5", f)
    return data


def test_failed_trials_one_line_each_and_invalid_samples_counted(tmp_path, capsys):
    data = _bad_dir(tmp_path)
    out = tmp_path / "report"
    rc = main(["evaluate", "--filter", "madgwick", "--data", str(data), "--out", str(out), "--jobs", "1"])
    assert rc == 3  # tables written for 01_a; the failures listed
    err = capsys.readouterr().err
    lines = err.splitlines()
    short = [ln for ln in lines if "02_b.hdf5" in ln]
    nan = [ln for ln in lines if "03_c.hdf5" in ln]
    assert short == [f"  {data / '02_b.hdf5'}: field 'imu_gyr': 10 samples (0.03 s at 285.7 Hz) is too short: at "
                     "least 285 samples (1 s, togglecf.data.broad.MIN_DURATION_S) are needed to evaluate a filter"]
    assert nan == [f"  {data / '03_c.hdf5'}: field 'acc': 120 of 600 samples (20.0%) are not finite (NaN/inf; first "
                   "at index 100); at most 10% may be (togglecf.data.broad.MAX_INVALID_FRACTION)"]
    assert f"note: {data / '01_a.hdf5'}: 30 IMU sample(s) not finite (acc 30); the filter skipped them " \
           "(a trial is refused above 10% per field)" in lines
    assert "{" not in err and "DataError" not in err  # no dict repr, no exception class names
    per_trial = pd.read_csv(out / "per_trial.csv", index_col=0)
    assert list(per_trial.index) == ["01_a"] and per_trial.loc["01_a", "n_invalid"] == 30
    assert per_trial["total"].notna().all()
    res = json.loads((out / "results.json").read_text())
    assert res["invalid_samples"] == {"01_a": {"gyr": 0, "acc": 30, "mag": 0, "samples": 30}}
    assert res["per_trial"]["01_a"]["n_invalid"] == 30 and res["max_invalid_fraction"] == 0.1
    assert set(res["failed_trials"]) == {"02_b", "03_c"}


def test_all_trials_failed_is_an_error_with_one_line_per_trial(tmp_path, capsys):
    data = _bad_dir(tmp_path)
    for cmd in (["evaluate", "--filter", "cf"], ["tune", "--filter", "cf", "--grid", "tau=0.3482,0.1732"]):
        assert main([*cmd, "--data", str(data), "--trials", "02,03", "--jobs", "1"]) == 1
        err = capsys.readouterr().err
        assert "{" not in err and "Traceback" not in err
        assert sum("02_b.hdf5: field 'imu_gyr': 10 samples" in ln for ln in err.splitlines()) == 1
        assert sum("03_c.hdf5: field 'acc': 120 of 600 samples (20.0%)" in ln for ln in err.splitlines()) == 1
    # evaluate: the lines, then one error line; tune: the error names the failures, one per line
    assert main(["evaluate", "--filter", "cf", "--data", str(data), "--trials", "02,03", "--jobs", "1"]) == 1
    assert "togglecf evaluate: error: no trial could be evaluated: all 2 selected trial(s) failed (listed above)" in \
        capsys.readouterr().err
    assert main(["tune", "--filter", "cf", "--grid", "tau=0.3482", "--data", str(data), "--trials", "02,03",
                 "--jobs", "1"]) == 1
    assert "togglecf tune: error: no trial was evaluated at every grid point; 2 failed:\n  " in capsys.readouterr().err


@pytest.mark.broad
def test_evaluate_and_tune_on_real_trials(broad_index, tmp_path, capsys):
    args = ["--data", str(broad_index.root), "--trials", "02,07", "--jobs", "2"]
    assert main(["evaluate", "--filter", "cf", *args, "--out", str(tmp_path / "e")]) == 0
    per_trial = pd.read_csv(tmp_path / "e" / "per_trial.csv", index_col=0)
    assert len(per_trial) == 2 and (per_trial["us_per_sample"] > 0).all()
    assert main(["tune", "--filter", "cf", "--grid", "tau=35.0,11.66,0.3482", *args]) == 0
    out = capsys.readouterr().out
    assert "TAGP of cf: {'tau':" in out





@pytest.mark.broad
def test_train_then_evaluate_toggling_on_unseen_trial(broad_index, tmp_path, capsys):
    cfg = tmp_path / "tiny.toml"
    cfg.write_text(TINY_TRAIN_TOML)
    models = tmp_path / "models"
    data = ["--data", str(broad_index.root)]
    assert main(["train", "--config", str(cfg), "--trials", "02,24,29", "--out", str(models), *data]) == 0
    gains = json.loads((models / "gains.json").read_text())
    assert set(gains) >= {"9d", "6d", "feature_schema_hash"}
    assert gains["9d"]["predictions"].startswith("out-of-fold")  # learned on CV models that never saw the trial
    assert gains["9d"]["trials"] == ["02_undisturbed_slow_rotation_B", "24_disturbed_tapping_A",
                                     "29_disturbed_stationary_magnet_B"]
    out = tmp_path / "eval"
    for extra in ([], ["--6d"]):
        assert main(["evaluate", "--filter", "toggling", "--models", str(models), "--trials", "07", "--out", str(out),
                     "--jobs", "1", *extra, *data]) == 0
        per_trial = pd.read_csv(out / "per_trial.csv", index_col=0)
        # a trained filter on a fast-rotation trial it never saw: far from the tens of degrees of a broken one
        assert per_trial.loc["07_undisturbed_fast_rotation_B", "total"] < 15.0
    assert "in-sample" not in capsys.readouterr().err  # 07 was never seen: no warning
    # scored on one of its own training trials (and a copy of it elsewhere): one warning line, the trial named
    copy = tmp_path / "copy"
    copy.mkdir()
    (copy / "trials.json").write_text((broad_index.root / "trials.json").read_text())
    src = broad_index.available["24_disturbed_tapping_A"]
    (copy / src.name).write_bytes(src.read_bytes())
    for where in (data, ["--data", str(copy)]):
        assert main(["evaluate", "--filter", "toggling", "--models", str(models), "--trials", "24", "--jobs", "1",
                     *where]) == 0
        warned = [ln for ln in capsys.readouterr().err.splitlines() if "in-sample" in ln]
        assert len(warned) == 1 and "1 of the 1 trials" in warned[0] and "24_disturbed_tapping_A" in warned[0]
    assert main(["evaluate", "--filter", "toggling", "--param", "tau_acc=0.1", "--models", str(models), *data]) == 1
    assert "takes no --param" in capsys.readouterr().err


def test_library_noise_is_dropped_and_the_rest_kept(capfd):
    """Native log lines and version/deprecation warnings of the tree libraries are dropped from stdout,
    stderr (file descriptor 2: native code) and Python warnings; other lines, errors included, pass."""
    with warnings.catch_warnings(record=True) as shown:
        warnings.simplefilter("always")  # every warning shown, but for those of the libraries
        with library_noise_filtered():
            _write_library_noise_and_real_lines()
    out, err = capfd.readouterr()
    assert out == "tl2cgen: object size\n"
    assert set(err.splitlines()) == {"[15:12:44] /src/c_api.cc:12: error: cannot open model", "equivalence check",
                                     "a real stderr line"}
    assert [str(w.message) for w in shown] == ["a real warning"]


def _write_library_noise_and_real_lines():
    os.write(2, b"[15:12:43] /tmp/x/libbuild/_deps/treelite-src/src/serializer.cc:202: The model you are loading "
                b"originated from a newer Treelite version; some functionalities may be unavailable.\n"
                b"Currently running Treelite version 4.1.2\nThe model checkpoint was generated from Treelite "
                b"version 4.8.1\n[15:12:44] /src/c_api.cc:12: error: cannot open model\nequivalence check\n")
    print("[15:12:43] /project/src/compiler/ast/split.cc:30: Parallel compilation disabled; all member trees")
    print("tl2cgen: object size")
    warnings.warn_explicit("treelite version 4.8.1 > 4.1.2", UserWarning, "core.py", 1, module="treelite.core")
    warnings.warn_explicit("[15:12:45] WARNING: /ws/src/learner.cc:740: deprecated parameter", UserWarning,
                           "x.py", 1, module="togglecf.embedded.forest_export")
    warnings.warn_explicit("a real warning", UserWarning, "x.py", 1, module="togglecf.embedded.forest_export")
    # one write: under capfd sys.stderr goes straight to the capture file, beside the filter thread's writes
    # of fd 2's lines; print() would write the text and its newline apart, and a thread's line could land between
    sys.stderr.write("a real stderr line\n")


@pytest.mark.slow
def test_export_prints_no_library_version_warnings(tiny_model_dir, mini_index, tmp_path, capfd):
    """`togglecf export` of a tiny model: its log is the command's own lines, no tree-library chatter
    (TL2cgen's embedded Treelite warns three lines per checkpoint of a newer Treelite)."""
    pytest.importorskip("tl2cgen")
    assert main(["export", "--models", str(tiny_model_dir), "--out", str(tmp_path / "emb"), "--format", "tl2cgen",
                 "--data", str(mini_index.root), "--trials", "24", "--no-riscv"]) == 0
    out, err = capfd.readouterr()
    assert "equivalence (≤ 1e-05)" in out and "OK" in out
    noise = [ln for ln in (out + err).splitlines()
             if re.search(r"Treelite version|deprecat|Parallel compilation|Warning:|\.cc:\d+:", ln, re.IGNORECASE)]
    assert noise == []


def test_results_json_stores_the_settings_as_json_fields(tmp_path):
    """results.json's ``settings``: a JSON object naming the settings class and each field (read back with
    json), not a Python repr a reader would have to parse."""
    data = make_broad_dir(tmp_path / "b", ["01_a"], ["01_a"])
    out = tmp_path / "report"
    assert main(["evaluate", "--filter", "cf", "--param", "tau=0.3482", "--data", str(data), "--out", str(out),
                 "--jobs", "1"]) == 0
    text = (out / "results.json").read_text()
    settings = json.loads(text)["settings"]
    assert settings["kind"].endswith("Settings") and settings["fields"]["tau"] == 0.3482
    assert "Settings(" not in text
