"""The Dask backend on a real ``LocalCluster`` (worker processes on 127.0.0.1): same TAGP and CV
metrics as the local backend, a worker killed mid-sweep, an interrupted sweep resumed, xgboost.dask."""
import json
import os
import signal

import numpy as np
import pytest

distributed = pytest.importorskip("distributed", reason="dask.distributed not installed: pip install 'togglecf[dask]'")

from togglecf.parallel.backend import DaskBackend, LocalBackend  # noqa: E402
from togglecf.cli.main import main  # noqa: E402
from togglecf.core.io import to_jsonable  # noqa: E402
from togglecf.run.scoring import grid_points  # noqa: E402
from togglecf.run.sweep import grid_search  # noqa: E402
from togglecf.run.sweep import ResultStore, journal_path, run_sweep  # noqa: E402
from togglecf.run.config import load_config  # noqa: E402
from togglecf.run.train import run_training  # noqa: E402
from conftest import TINY_TRAIN_TOML  # noqa: E402

pytestmark = pytest.mark.broad

TRIALS = "02,07,24"
GRID = {"Kp": [0.5, 0.7, 0.9], "Ki": [0.0, 0.0015]}


@pytest.fixture(scope="module")
def cluster():
    from distributed import Client, LocalCluster

    with LocalCluster(n_workers=2, threads_per_worker=1, processes=True, host="127.0.0.1",
                      dashboard_address=None) as c, Client(c) as client:
        yield c, client


@pytest.fixture(scope="module")
def local_tune(broad_index):
    names = broad_index.select(TRIALS)
    return names, grid_search(broad_index, names, "mahony", GRID, backend=LocalBackend(2))


def _wait_workers(client, n=2, timeout=60):
    client.wait_for_workers(n, timeout=timeout)


def test_tune_on_dask_equals_local(broad_index, cluster, local_tune, capsys):
    _, client = cluster
    names, local = local_tune
    dask = grid_search(broad_index, names, "mahony", GRID, backend=DaskBackend(client), chunk_size=0)
    assert dask.params == local.params
    assert np.array_equal(dask.mean_total, local.mean_total)  # bit-identical TAGP surface
    assert dask.per_trial == local.per_trial
    # the command line, pointed at the cluster's scheduler address
    args = ["tune", "--filter", "mahony", "--grid", "Kp=0.5,0.7,0.9", "--grid", "Ki=0,0.0015",
            "--data", str(broad_index.root), "--trials", TRIALS, "--backend", "dask", "--scheduler", client.scheduler.address]
    assert main(args) == 0
    captured = capsys.readouterr()
    assert f"TAGP of mahony: {local.params}" in captured.out and "backend: dask at" in captured.err


def test_worker_killed_mid_sweep_still_completes(broad_index, cluster, local_tune):
    _, client = cluster
    names, local = local_tune
    _wait_workers(client)
    killed = []

    def kill_one(n_done):
        if n_done == 2 and not killed:  # after the second finished task, with most still queued or running
            pid = next(iter(client.run(os.getpid).values()))
            os.kill(pid, signal.SIGKILL)  # no graceful hand-off; the nanny starts a new worker process
            killed.append(pid)

    res = grid_search(broad_index, names, "mahony", GRID, backend=DaskBackend(client), chunk_size=1,
                      on_result=kill_one)
    assert killed
    assert not res.failed and res.params == local.params
    assert np.array_equal(res.mean_total, local.mean_total) and res.per_trial == local.per_trial
    _wait_workers(client)
    assert killed[0] not in client.run(os.getpid).values()  # the nanny replaced the killed process


class Stop(Exception):
    pass


def test_interrupted_dask_sweep_resumes_with_only_the_missing_points(broad_index, cluster, local_tune, tmp_path):
    _, client = cluster
    names, local = local_tune
    _wait_workers(client)
    params = grid_points(GRID)
    path = journal_path(tmp_path)

    def stop(n_done):
        if n_done == 4:
            raise Stop

    with ResultStore(path) as store, pytest.raises(Stop):
        run_sweep(broad_index, names, "mahony", params, backend=DaskBackend(client), store=store, chunk_size=1,
                  on_result=stop)
    with ResultStore(path) as store:
        n_done = len(store.done)
        assert n_done == 4
        second = run_sweep(broad_index, names, "mahony", params, backend=DaskBackend(client), store=store,
                           chunk_size=1)
    total = len(params) * len(names)
    assert second.reused == n_done and second.computed == total - n_done
    # resumed + computed results give the local run's grid surface, bit for bit
    mean_total = [np.mean([r.errors["total"] for r in res.values()]) for res in second.results]
    assert np.array_equal(np.array(mean_total), local.mean_total.ravel())


def _tiny_cfg(**run):
    import tomllib

    cfg = load_config(tomllib.loads(TINY_TRAIN_TOML))
    cfg["gains"]["learn"] = False
    cfg["run"].update(run)
    return cfg


def _strip_seconds(cv):
    cv = {**cv, "folds": [{k: v for k, v in f.items() if k != "seconds"} for f in cv["folds"]]}
    return cv


def test_train_cv_on_dask_equals_local(broad_index, cluster, tmp_path):
    _, client = cluster
    _wait_workers(client)
    local = run_training(_tiny_cfg(), data_dir=broad_index.root, trials=TRIALS, out=tmp_path / "local", verbose=False)
    dask = run_training(_tiny_cfg(), data_dir=broad_index.root, trials=TRIALS, out=tmp_path / "dask", verbose=False,
                        backend=DaskBackend(client))
    assert _strip_seconds(dask["cv"]) == _strip_seconds(local["cv"])  # identical CV metrics, fold by fold
    assert np.array_equal(dask["data"].X, local["data"].X, equal_nan=True)  # features computed on the workers
    for f in ("classifier.ubj", "acc_x.ubj", "mag_z.ubj"):
        assert (tmp_path / "dask" / f).read_bytes() == (tmp_path / "local" / f).read_bytes()
    # the command line with the backend in the config's [run] table
    cfg = tmp_path / "tiny.toml"
    cfg.write_text(TINY_TRAIN_TOML.replace("[run]", f'[run]\nbackend = "dask"\nscheduler = "{client.scheduler.address}"')
                   .replace("[gains]\n", "[gains]\nlearn = false\n"))
    assert main(["train", "--config", str(cfg), "--data", str(broad_index.root), "--trials", TRIALS,
                 "--out", str(tmp_path / "cli")]) == 0
    meta = json.loads((tmp_path / "cli" / "metadata.json").read_text())
    assert meta["config"]["run"]["backend"] == "dask"
    assert _strip_seconds(meta["cv"]) == _strip_seconds(json.loads(json.dumps(to_jsonable(local["cv"]))))


def test_final_fit_with_xgboost_dask(broad_index, cluster, tmp_path):
    """xgboost.dask is not bit-identical to single-node XGBoost (the quantile sketch is merged across
    workers, so histogram cut points differ slightly, histogram sums are added in another order and row
    subsampling draws per worker), so this checks agreement on the training windows against the spread
    between two single-node fits that differ only in the seed (0 vs 1, measured on these trials: 96.1 %
    same predicted state, regressor RMSEs within 0.4 %; xgboost.dask vs single-node measured 97.0 % and
    0.6 %): >= 93 % same state and RMSEs within 3 %."""
    _, client = cluster
    _wait_workers(client)
    local = run_training(_tiny_cfg(), data_dir=broad_index.root, trials=TRIALS, out=tmp_path / "l", cv=False,
                         verbose=False)
    run_training(_tiny_cfg(distributed_fit=True), data_dir=broad_index.root, trials=TRIALS,
                        out=tmp_path / "d", cv=False, verbose=False, backend=DaskBackend(client))
    from togglecf.learn.models import load_bundle, regression_metrics

    data = local["data"]
    rows = np.flatnonzero(data.train_mask)
    bl, bd = load_bundle(tmp_path / "l"), load_bundle(tmp_path / "d")
    X = data.X[rows]
    agree = np.mean(bl.classifier.predict(X) == bd.classifier.predict(X))
    print(f"xgboost.dask vs single-node: state agreement {agree:.4f}")
    assert agree >= 0.93, agree
    for t in ("acc", "mag"):
        y = getattr(data, f"eta_{t}")[rows]
        rl = regression_metrics(y, bl.regressors[t].predict(X))["rmse"]
        rd = regression_metrics(y, bd.regressors[t].predict(X))["rmse"]
        print(f"{t} RMSE single-node {rl:.4f}, xgboost.dask {rd:.4f}")
        assert abs(rd - rl) < 0.03 * rl, (t, rl, rd)


def test_pruning_sweep_on_dask_equals_inline(broad_index, cluster, tmp_path):
    """`togglecf prune` with every (point, fold) a Dask task: the same rows and per-trial errors as
    the in-process sweep (sizes too: the same trees are measured, only where differs; the
    timings are the only columns allowed to differ)."""
    from togglecf.run import prune
    from togglecf.parallel.backend import InlineBackend

    _, client = cluster
    (tmp_path / "tiny.toml").write_text(TINY_TRAIN_TOML)
    run_training(str(tmp_path / "tiny.toml"), data_dir=broad_index.root, trials="02,07,10,24",
                 out=tmp_path / "models", cv=True, verbose=False)
    points = [prune.PrunePoint(3, 2, 3, 2, 0, True), prune.PrunePoint(2, 2, 2, 2, 6)]
    kw = dict(folds=2, inner_folds=2, data_dir=broad_index.root, riscv=False, log=lambda m: None)
    here = prune.pruning_sweep(tmp_path / "models", tmp_path / "inline", points, backend=InlineBackend(), **kw)
    there = prune.pruning_sweep(tmp_path / "models", tmp_path / "dask", points, backend=DaskBackend(client), **kw)
    timing = {"us_per_prediction", "seconds"}
    for a, b in zip(here, there):
        assert {k: v for k, v in a.items() if k not in timing} == {k: v for k, v in b.items() if k not in timing}
    per = [sorted((r["trial"], r["total"]) for r in json.loads(line)["per_trial"])
           for d in ("inline", "dask") for line in (tmp_path / d / "sweep_rows.jsonl").read_text().splitlines()]
    assert sorted(per[:2]) == sorted(per[2:])
