"""Backends without a cluster: the resumable sweep journal, failed trials, clear backend errors."""
import json
import os
import subprocess
import sys
import types

import pandas as pd
import pytest

from togglecf import source_digest
from togglecf.parallel import backend as be
from togglecf.cli.main import main
from togglecf.data.broad import DatasetIndex
from togglecf.run.sweep import evaluate_trials
from togglecf.run.sweep import ResultStore, journal_path, run_sweep
from test_data import make_broad_dir



def _grid():
    return [{"tau": t} for t in (3.498, 1.748, 0.6982, 0.3482, 0.1732)]


class Stop(Exception):
    pass


def _stop_after(k):
    def cb(n):
        if n >= k:
            raise Stop
    return cb


@pytest.fixture
def synth(tmp_path):
    return DatasetIndex.from_dir(make_broad_dir(tmp_path / "b", ["01_a", "02_b", "03_c"], ["01_a", "02_b", "03_c"]))


def _errors(results):
    return [{n: r.errors for n, r in res.items()} for res in results]


@pytest.mark.parametrize("jobs", [1, 2])
def test_interrupted_sweep_resumes_with_only_the_missing_points(synth, tmp_path, jobs):
    names, params = list(synth.available), _grid()
    full = evaluate_trials(synth, names, "cf", params, jobs=1)
    path = journal_path(tmp_path / "out")
    with ResultStore(path) as store, pytest.raises(Stop):
        run_sweep(synth, names, "cf", params, backend=be.LocalBackend(jobs), store=store, chunk_size=2,
                  on_result=_stop_after(3))
    with ResultStore(path) as store:
        n_done = len(store.done)
        assert 0 < n_done < len(names) * len(params)
        second = run_sweep(synth, names, "cf", params, backend=be.LocalBackend(jobs), store=store, chunk_size=2)
    assert second.reused == n_done and second.computed == len(names) * len(params) - n_done
    assert _errors(second.results) == _errors(full)  # resumed values are bit-identical (repr floats)
    with ResultStore(path) as store:  # a third run computes nothing
        third = run_sweep(synth, names, "cf", params, backend=be.LocalBackend(jobs), store=store)
    assert third.computed == 0 and _errors(third.results) == _errors(full)
    with ResultStore(path) as store:  # another mode (6D) is another key: computed anew
        assert run_sweep(synth, names, "cf", params[:1], use_mag=False, store=store,
                         backend=be.LocalBackend(1)).computed == len(names)


def test_changed_trial_file_is_recomputed(synth, tmp_path):
    names, params = list(synth.available), _grid()[:2]
    path = journal_path(tmp_path / "out")
    with ResultStore(path) as store:
        run_sweep(synth, names, "cf", params, backend=be.LocalBackend(1), store=store)
    f = synth.available["02_b"]
    f.touch()  # same content, new mtime: its points are computed again, the others reused
    import os
    os.utime(f, ns=(f.stat().st_atime_ns, f.stat().st_mtime_ns + 10**9))
    with ResultStore(path) as store:
        r = run_sweep(synth, names, "cf", params, backend=be.LocalBackend(1), store=store)
    assert r.computed == len(params) and r.reused == 2 * len(params)


def test_trial_that_fails_to_load_is_reported_and_the_sweep_goes_on(synth, tmp_path, capsys):
    (synth.root / "03_c.hdf5").write_bytes(b"not an hdf5 file")
    names, params = list(synth.available), _grid()
    r = run_sweep(synth, names, "cf", params, backend=be.LocalBackend(2), on_error="report")
    assert set(r.failed) == {"03_c"} and "03_c" in r.failed and r.failed["03_c"]
    assert all(set(res) == {"01_a", "02_b"} for res in r.results)
    assert sorted({n for n, _ in r.missing}) == ["03_c"] and len(r.missing) == len(params)
    with pytest.raises(Exception):
        evaluate_trials(synth, names, "cf", params, jobs=1)
    out = tmp_path / "tune"
    code = main(["tune", "--filter", "cf", "--grid", "tau=3.498,0.3482", "--data", str(synth.root), "--out", str(out)])
    err = capsys.readouterr().err
    assert code == 3 and "03_c" in err and "failed" in err
    res = json.loads((out / "results.json").read_text())
    assert list(res["failed_trials"]) == ["03_c"]
    assert list(pd.read_csv(out / "per_trial.csv", index_col=0).index) == ["01_a", "02_b"]


def test_cli_tune_resumes_from_its_out_dir(synth, tmp_path, capsys):
    out = tmp_path / "tune"
    args = ["tune", "--filter", "cf", "--grid", "tau=3.498,0.3482", "--data", str(synth.root), "--out", str(out)]
    assert main(args) == 0
    first = (out / "per_trial.csv").read_text()
    assert main(args) == 0
    assert "resuming: 6 results" in capsys.readouterr().err
    assert (out / "per_trial.csv").read_text() == first
    assert main(args + ["--no-resume"]) == 0 and "resuming" not in capsys.readouterr().err


def test_backend_errors_are_clear(monkeypatch, synth, capsys):
    with pytest.raises(be.BackendError, match="unknown backend"):
        be.make_backend("spark")
    monkeypatch.setitem(sys.modules, "distributed", None)  # as if dask were not installed
    with pytest.raises(be.BackendError, match=r"pip install 'togglecf\[dask\]'"):
        be.make_backend("dask", "tcp://127.0.0.1:8786")
    assert main(["tune", "--filter", "cf", "--grid", "tau=0.3482", "--data", str(synth.root),
                 "--backend", "dask", "--scheduler", "tcp://127.0.0.1:8786"]) == 1
    assert "togglecf[dask]" in capsys.readouterr().err


def test_unreachable_scheduler_is_one_clear_line(monkeypatch, synth, capsys):
    pytest.importorskip("distributed", reason="dask.distributed not installed (pip install 'togglecf[dask]')")
    monkeypatch.setattr(be, "CONNECT_TIMEOUT_S", 1.0)
    assert main(["tune", "--filter", "cf", "--grid", "tau=0.3482", "--data", str(synth.root),
                 "--backend", "dask", "--scheduler", "tcp://127.0.0.1:9"]) == 1
    err = capsys.readouterr().err
    assert "cannot reach Dask scheduler at tcp://127.0.0.1:9" in err and "dask scheduler" in err
    assert "Traceback" not in err


def test_store_serves_a_trial_under_another_index_by_its_name_there(synth, tmp_path):
    """The store of `make run` is shared by a study on one directory and one on several: a trial file's
    result comes back under the name and groups the second index gives it ("<dataset>/<trial>")."""
    from togglecf.data.broad import open_index

    names, params = list(synth.available), _grid()[:2]
    path = tmp_path / "shared.jsonl"
    with ResultStore(path) as store:
        first = run_sweep(synth, names, "cf", params, backend=be.LocalBackend(1), store=store)
    multi = open_index([str(synth.root), str(make_broad_dir(tmp_path / "other", ["04_d"], ["04_d"]))])
    both = multi.select(None)
    with ResultStore(path) as store:
        second = run_sweep(multi, both, "cf", params, backend=be.LocalBackend(1), store=store)
    assert second.reused == len(names) * len(params) and second.computed == len(params)  # only the new trial
    prefix = synth.root.name
    for i in range(len(params)):
        for n in names:
            r = second.results[i][f"{prefix}/{n}"]
            assert r.trial == f"{prefix}/{n}" and r.groups == multi.trial_groups(f"{prefix}/{n}")
            assert r.errors == first.results[i][n].errors


def test_numba_imported_first_still_caches_in_the_content_keyed_directory():
    """A script that imports numba before togglecf (numba reads NUMBA_CACHE_DIR at its import): the package's
    kernels still cache in the directory keyed on the package's content, not beside their sources (keyed on each
    kernel's own file, which runs stale code after an edit of a function inlined from another file)."""
    code = ("import numba, os\n"
            "import togglecf\n"
            "from numba.core import config\n"
            "from togglecf.filters.timeconst import gain_from_tau\n"
            "assert config.CACHE_DIR == os.environ['NUMBA_CACHE_DIR'], config.CACHE_DIR\n"
            "assert togglecf.source_digest()[:16] in config.CACHE_DIR\n"
            "assert gain_from_tau._cache._cache_path.startswith(config.CACHE_DIR), gain_from_tau._cache._cache_path\n")
    env = {k: v for k, v in os.environ.items() if k != "NUMBA_CACHE_DIR"}
    done = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True)
    assert done.returncode == 0, done.stderr


def test_source_digest_follows_the_source(tmp_path):

    (tmp_path / "pkg").mkdir()
    (tmp_path / "pkg" / "a.py").write_text("x = 1\n")
    (tmp_path / "pkg" / "k.c").write_text("int x;\n")
    d0 = source_digest(tmp_path)
    (tmp_path / "pkg" / "notes.txt").write_text("not code")  # not a source file: same key
    assert source_digest(tmp_path) == d0
    (tmp_path / "pkg" / "k.c").write_text("int y;\n")
    assert source_digest(tmp_path) != d0
    assert len(source_digest()) == 64


def test_local_backend_runs_in_process_inside_a_daemon(monkeypatch):
    """A Dask worker is a daemonic process and may not start a pool: the tasks run in it, in order."""
    import multiprocessing as mp

    monkeypatch.setattr(mp.current_process(), "daemon", True, raising=False)
    out = list(be.LocalBackend(2).run(_square, [(k, (k,)) for k in range(4)]))
    assert [(o.key, o.value) for o in out] == [(k, k * k) for k in range(4)]


def _square(x):
    return x * x


def _negate(x):
    return -x


def _fail(name):
    raise ValueError(f"{name}: bad")


@pytest.mark.parametrize("backend", [be.InlineBackend(), be.LocalBackend(2), be.LocalBackend(2, "forkserver")],
                         ids=["inline", "fork", "forkserver"])
def test_run_tasks_mixes_functions_and_returns_in_task_order(backend):
    # make run puts the study's folds, the left-out datasets and the pretrained training on one pool
    tasks = [be.Task(("b", k), _square, (k,)) for k in range(3)] + [be.Task("a", _negate, (5,))]
    done = be.run_tasks(backend, tasks)
    assert list(done) == [("b", 0), ("b", 1), ("b", 2), "a"]
    assert list(done.values()) == [0, 1, 4, -5]
    with pytest.raises(ValueError, match="trial 7: bad"):
        be.run_tasks(backend, tasks + [be.Task("c", _fail, ("trial 7",))])


def test_a_failed_handshake_is_tried_once_more_then_reported(monkeypatch):
    """distributed's Client asserted on the scheduler's first reply once in the test suite (a loaded machine):
    DaskBackend connects once more; failing every time is an unreachable scheduler (BackendError's one line)."""
    calls = []

    class FlakyClient:
        scheduler = types.SimpleNamespace(address="tcp://h:8786")

        def __init__(self, address, timeout):
            calls.append(address)
            if len(calls) < fails_before_ok:
                raise AssertionError

    monkeypatch.setitem(sys.modules, "distributed", types.SimpleNamespace(Client=FlakyClient))
    fails_before_ok = 2
    assert be.DaskBackend("tcp://h:8786").address == "tcp://h:8786" and len(calls) == 2
    calls.clear()
    fails_before_ok = be.CONNECT_ATTEMPTS + 1
    with pytest.raises(be.BackendError, match="cannot reach Dask scheduler at tcp://h:8786.*handshake failed"):
        be.DaskBackend("tcp://h:8786")
    assert len(calls) == be.CONNECT_ATTEMPTS
