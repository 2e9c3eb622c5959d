"""The README's main job (`make run`): the held-out study on every BROAD trial found, then the
cross-dataset protocol.

1. Finds BROAD (downloading it into ./data/broad first when it is nowhere to be found, and saying
   so) and runs the held-out study (``togglecf.run.study``): per fold, train the models and learn
   the gains on the training trials, evaluate the learned filters and all baselines on the
   held-out trials; writes reports/study/ (summary.md, tables, plots). With ``--full`` the study
   also runs its ablations (the config's ``[study] ablations``: most learn gains or models again;
   and the 6D rows), which lengthens it; the rows both have are the same numbers.
2. Rate: the same held-out trials 3x decimated (95.2 Hz), each scored with the models of the fold
   that held it out -> reports/transfer/rate.md.
3. With ``--full``, when the phone data (BROAD layout; ``$TOGGLECF_PHONE_DATA``, else ``tyrex_nexus5``
   beside the BROAD directory) is there: models trained on all of BROAD scored on every phone trial ->
   reports/transfer/phone.md, and the held-out study on BROAD + phone together (folds by whole trial
   over both; no ablations) -> reports/study_both/ (per-dataset rows in its tables). Step 4 asks the
   cross-dataset question more cleanly, so the main job leaves these out.
4. Leave one dataset out, over BROAD and every directory in BROAD's layout beside it (today the
   Nexus 5 and the iPhone 4S data): train on all the others, score the one left out; the learned
   filters beside their cores with learning off, per dataset and group (``togglecf.run.lodo``)
   -> reports/lodo/lodo.md (9D: the learned filters' 9D gains; the harm to find was in the heading).
5. The pretrained learned VQF: the same recipe trained on every dataset present, with its model card
   and the no-harm check of step 4 (``togglecf.run.pretrained``) -> reports/pretrained/
   (learned_vqf.npz, MODEL_CARD.md); ``python pipelines/ship_pretrained.py`` puts them in the package
   when every check passed, and says whether the package's copy was the same.
6. With ``--full``: the headroom over VQF on every dataset of step 4 (``togglecf.run.headroom``: VQF at its
   defaults, its two time constants tuned held out and as oracles, per-state time constants driven by the
   true motion labels, VQF's offline estimate) -> reports/headroom/ (as ``python pipelines/headroom.py``).
7. With ``--full``, your sensor, measured: on each dataset alone (folds within it), the learned VQF
   re-learned from step 4's models that never saw it and trained from scratch, on 2, 4, 8 and all
   training recordings, against VQF at its defaults and tuned on the same recordings
   (``togglecf.run.per_sensor``, also ``pipelines/per_sensor.py``) -> reports/per_sensor/per_sensor.md; and the
   kept-back check's split, each half re-learned on and the other scored -> per_sensor_half.md, and both
   with the field-change back-off's scale searched in the scratch training too (the re-learning searches it by
   default) -> per_sensor_field_change.md, per_sensor_half_field_change.md.
8. With ``--full``: what could set VQF's two time constants on a dataset left out (``togglecf.run.travel``:
   trial statistics of the sensor's own signals, a reference-free self-tuning, and their ceilings, each
   scored on the second half of every trial) -> reports/travel/ (as ``python pipelines/travel.py``).

Computed once, on one pool: the baseline grids of step 1 and Madgwick's grid of step 4 run first
(their results are kept in build/cache/, keyed on the package's source and each trial file, and
shared by the steps, so a trial's grid is never computed twice); then the study's folds, the
left-out datasets of step 4 and the training of step 5 run as tasks of one process pool, the
longest first (``run_together``), so no core waits for the last task of a step; the reports are
written from their results. The learned filters' kernels are compiled while the grids run, one
process per family (``togglecf.run.warmup``), so the pool's workers load them from numba's cache
instead of each compiling them at once. The gain searches reuse an evaluation they have made before
(``toggling.gains.EvaluationMemo``). Each step's wall time is logged, and all of them at the end.

    python pipelines/main.py [--skip-study]    # --skip-study: steps 2-5 on an existing reports/study
    python pipelines/main.py --full            # + the study's ablations, steps 3, 6, 7 and 8: what every table in
                                               #   docs/results comes from
    python pipelines/main.py --lodo-only       # steps 4 and 5 alone
    python pipelines/main.py --pretrained-only # step 5 alone, on an existing reports/lodo/lodo.json
    python pipelines/main.py --backend dask --scheduler tcp://HOST:8786   # the tasks on a cluster
"""
import argparse
import json
import logging
import os
import sys
import time
from contextlib import contextmanager, nullcontext
from dataclasses import replace
from pathlib import Path

from togglecf import source_digest
from togglecf.core.config import BACKENDS
from togglecf.core.io import atomic_write_json, atomic_write_text
from togglecf.core.log import setup_logging
from togglecf.data.broad import DataNotFoundError, DatasetIndex, resolve_data_dir
from togglecf.data.download import download_broad
from togglecf.parallel.backend import BackendError, LocalBackend, Task, make_backend, run_tasks
from togglecf.run.config import load_config
from togglecf.run.headroom import headroom_settings, run_headroom
from togglecf.run.lodo import dataset_dirs, lodo_json, lodo_table, plan_lodo
from togglecf.run.per_sensor import (HALF, PerSensorConfig, base_models, per_sensor, per_sensor_json, per_sensor_table,
                                     with_field_change)
from togglecf.run.pretrained import train_pretrained_models, write_pretrained
from togglecf.run.study import load_study_config, plan_study, run_study
from togglecf.run.sweep import ResultStore
from togglecf.run.train import run_training
from togglecf.run.warmup import start_compiling
from togglecf.run.travel import run_travel, travel_settings
from togglecf.run.transfer import models_transfer, results_json, study_transfer, transfer_table, write_decimated

DEFAULT_DOWNLOAD_DIR = Path("data/broad")
STUDY_DIR = Path("reports/study")
TRANSFER_DIR = Path("reports/transfer")
BOTH_DIR = Path("reports/study_both")
LODO_DIR = Path("reports/lodo")
PRETRAINED_DIR = Path("reports/pretrained")
PER_SENSOR_DIR = Path("reports/per_sensor")
LODO_BUILD_DIR = Path("build/lodo")
HEADROOM_DIR = Path("reports/headroom")
TRAVEL_DIR = Path("reports/travel")
CACHE_DIR = Path("build/cache")
log = logging.getLogger("togglecf.main")


def result_store() -> ResultStore:
    """The classic filters' results shared by the steps (the study's baseline grids, the two-dataset
    study's, Madgwick's TAGP of each left-out dataset): each (filter, parameters, trial file) is
    computed once. Keyed on the package's source content (``togglecf.source_digest``), so a code change starts
    an empty store; an old store is simply not read again."""
    return ResultStore(CACHE_DIR / f"classic-{source_digest()[:16]}.jsonl")


#: step -> wall time [s] of this run (the time goal of `make run`)
STEP_TIMES: dict = {}


@contextmanager
def step(name: str):
    """Logs the wall time of a step of the job and keeps it in ``STEP_TIMES``."""
    t0 = time.perf_counter()
    yield
    STEP_TIMES[name] = time.perf_counter() - t0
    log.info(f"step {name}: {STEP_TIMES[name] / 60:.1f} min")


def study_config(full: bool):
    """The study's config (``togglecf/configs/study.toml``); without ``full`` none of its ablations run:
    the learned rows and the baselines, the same numbers as with them (each row is computed on its own)."""
    cfg = load_study_config()
    return cfg if full else replace(cfg, ablations=())


def data_dir() -> Path:
    try:
        return resolve_data_dir(None)
    except DataNotFoundError as exc:
        print(f"{exc}\n\nBROAD not found: downloading it into {DEFAULT_DOWNLOAD_DIR} first.", file=sys.stderr)
        return download_broad(DEFAULT_DOWNLOAD_DIR)


def phone_dir(broad: Path) -> Path | None:
    d = Path(os.environ.get("TOGGLECF_PHONE_DATA") or Path(broad).resolve().parent / "tyrex_nexus5")
    return d if (d / "trials.json").is_file() else None


def _write(name, per, index, what, command):
    TRANSFER_DIR.mkdir(parents=True, exist_ok=True)
    text = transfer_table(per, index, what, command)
    atomic_write_text(TRANSFER_DIR / f"{name}.md", text)
    atomic_write_json(TRANSFER_DIR / f"{name}.json", results_json(per))
    print(text)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0], epilog=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--skip-study", action="store_true", help="use the existing reports/study (steps 2-5 only)")
    p.add_argument("--full", action="store_true", help="also the study's ablations, the sensor transfer, the "
                   "two-dataset study and the per-sensor re-learning: every table of docs/results (the ablations "
                   "learn gains and models again)")
    p.add_argument("--lodo-only", action="store_true", help="steps 4 and 5 alone: leave one dataset out, pretrained")
    p.add_argument("--pretrained-only", action="store_true", help="step 5 alone (on an existing reports/lodo)")
    p.add_argument("--backend", choices=BACKENDS, default="local",
                   help="where the folds and left-out datasets run: local process pool (default) or dask")
    p.add_argument("--scheduler", metavar="ADDR", help="Dask scheduler address (with --backend dask; its workers "
                   "must read the data and write build/ and reports/: a shared filesystem)")
    args = p.parse_args(argv)
    try:
        backend = make_backend(args.backend, args.scheduler) if args.backend == "dask" else None  # None: local pools
    except BackendError as exc:
        p.error(str(exc))
    broad = data_dir()
    command = "python pipelines/main.py" + (" --full" if args.full else "")
    t0 = time.perf_counter()
    with backend or nullcontext(), result_store() as store:
        if args.pretrained_only:
            pretrained(broad)
            return 0
        # the learned filters' kernels compiled beside the grids, not by every worker at once (run.warmup)
        compiling = start_compiling() if backend is None else None
        if args.skip_study and not (STUDY_DIR / "results.json").is_file():
            p.error(f"--skip-study: no study in {STUDY_DIR} (run without --skip-study first)")
        study = None
        if not (args.skip_study or args.lodo_only):
            study = plan_study(study_config(args.full), data_dir=broad, out_dir=STUDY_DIR)
            with step("study grids"):
                study.evaluate_grids(store)
        lodo = plan_datasets_out(broad, store)
        if compiling is not None:
            with step("kernels compiled ahead (beside the grids)"):
                compiling.wait()
        done = run_together(study, lodo, dataset_dirs(broad), backend)
        if study is not None:
            with step("study report"):
                study.finish(done)
        if not args.lodo_only:
            with step("rate"):
                rate(broad, command)
            phone = phone_dir(broad)
            if args.full and phone is None:
                log.warning("phone data not found (set TOGGLECF_PHONE_DATA or put it beside BROAD as tyrex_nexus5): "
                            "the sensor transfer and the two-dataset study are skipped")
            elif args.full:
                sensor(broad, phone, command)
                both_datasets(broad, phone, store, backend)
        if lodo is not None:
            write_lodo(lodo.finish(done), lodo.dirs, command)
        pretrained(broad, trained=True)
        if args.full and not args.lodo_only:
            headroom(broad, store, command)
        if args.full and lodo is not None:
            each_sensor(lodo.dirs, command, store)
        if args.full and not args.lodo_only:
            what_travels(broad, command)
    log.info("make run: " + ", ".join(f"{k} {v / 60:.1f}" for k, v in STEP_TIMES.items())
             + f"; total {(time.perf_counter() - t0) / 60:.1f} min")
    return 0


def run_together(study, lodo, dirs, backend=None) -> dict:
    """The study's folds, the left-out datasets and the pretrained model's training (on ``dirs``) as tasks
    of one pool (``backend``; default: a local process pool on every core), the longest first: no worker
    waits for the last task of one step while another step has work. Returns key -> value of every task."""
    tasks = [Task("pretrained", train_pretrained_models, (dirs, PRETRAINED_DIR))]
    tasks += (lodo.tasks if lodo is not None else []) + (study.tasks() if study is not None else [])
    # forkserver: the tasks train XGBoost, whose OpenMP runtime does not survive a fork (LocalBackend)
    backend = backend or LocalBackend(study.jobs if study is not None else None, start_method="forkserver")
    what = ", ".join(w for w, here in (("study folds", study), ("left-out datasets", lodo), ("pretrained", True))
                     if here is not None)
    log.info(f"{len(tasks)} tasks ({what}) on {backend.describe()}")
    with step("tasks"):
        return run_tasks(backend, tasks, desc="make run", unit="task")


def rate(broad: Path, command: str) -> None:
    log.info("rate: the held-out trials 3x decimated, each with the models of its fold")
    dec = write_decimated(DatasetIndex.from_dir(broad), Path("build/data/broad_decimated_3x"), 3)
    _write("rate", study_transfer(STUDY_DIR, DatasetIndex.from_dir(dec)), DatasetIndex.from_dir(dec),
           f"each fold's models of `{STUDY_DIR}` on its own test trials, every 3 samples averaged (95.2 Hz)", command)


def pretrained(broad: Path, trained: bool = False) -> None:
    """The pretrained learned VQF's file and card in reports/pretrained (``trained``: its models are there,
    from ``run_together``; else trained here first)."""
    lodo_file = LODO_DIR / "lodo.json"
    lodo = json.loads(lodo_file.read_text()) if lodo_file.is_file() else None
    if lodo is None:
        log.warning(f"{lodo_file} not found: the model card will have no leave-one-dataset-out check")
    with step("pretrained"):
        if not trained:
            train_pretrained_models(dataset_dirs(broad), PRETRAINED_DIR)
        path = write_pretrained(dataset_dirs(broad), PRETRAINED_DIR, lodo)
    print((PRETRAINED_DIR / "MODEL_CARD.md").read_text())
    log.info(f"pretrained learned VQF: {path}; `python pipelines/ship_pretrained.py` puts it in the package")


def plan_datasets_out(broad: Path, store: ResultStore):
    """Leave one dataset out over BROAD and the datasets beside it, up to its tasks (``run.lodo.plan_lodo``,
    9D gains); None when BROAD is alone."""
    dirs = dataset_dirs(broad)
    if len(dirs) < 2:
        log.warning(f"no other dataset in BROAD's layout beside {broad}: leave one dataset out skipped")
        return None
    cfg = load_config()
    cfg["gains"]["modes"] = ["9d", "vqf_9d"]
    with step("leave-one-dataset-out grids"):
        return plan_lodo(dirs, LODO_BUILD_DIR, cfg, store=store)


def write_lodo(results: dict, dirs, command: str) -> None:
    """reports/lodo from the left-out datasets' results (``run.lodo.LodoPlan.finish``)."""
    LODO_DIR.mkdir(parents=True, exist_ok=True)
    text = lodo_table(results, dirs, command)
    atomic_write_text(LODO_DIR / "lodo.md", text)
    atomic_write_json(LODO_DIR / "lodo.json", lodo_json(results))
    print(text)


def each_sensor(dirs, command: str, store: ResultStore) -> None:
    """Step 7 (``--full``): the learned VQF re-learned on each dataset's own recordings, from the left-out
    datasets' models of step 4 (``run.per_sensor``): the learning curve -> reports/per_sensor/per_sensor.md,
    the kept-back check's split (``HALF``) -> per_sensor_half.md, and both with the field-change back-off's
    scale searched in the scratch training too (``with_field_change``; the re-learning searches it by default)
    -> per_sensor_field_change.md, per_sensor_half_field_change.md."""
    PER_SENSOR_DIR.mkdir(parents=True, exist_ok=True)
    for name, settings, config in (("per_sensor", PerSensorConfig(), None), ("per_sensor_half", HALF, None),
                                   ("per_sensor_field_change", PerSensorConfig(), with_field_change()),
                                   ("per_sensor_half_field_change", HALF, with_field_change())):
        with step(name.replace("_", " ")):
            out = Path("build") / name
            results = per_sensor(dirs, out, base_models(dirs, LODO_BUILD_DIR, out), settings, config=config,
                                 store=store)
        text = per_sensor_table(results, dirs, command)
        atomic_write_text(PER_SENSOR_DIR / f"{name}.md", text)
        atomic_write_json(PER_SENSOR_DIR / f"{name}.json", per_sensor_json(results))
        print(text)


def headroom(broad: Path, store: ResultStore, command: str) -> None:
    """reports/headroom on BROAD and every dataset beside it (``run.headroom``; the core's grid in ``store``)."""
    with step("headroom"):
        run_headroom(dataset_dirs(broad), HEADROOM_DIR, headroom_settings(), command, store=store)
    print((HEADROOM_DIR / "headroom.md").read_text())


def what_travels(broad: Path, command: str) -> None:
    """Step 8 (``--full``): reports/travel on BROAD and every dataset beside it (``run.travel``)."""
    dirs = dataset_dirs(broad)
    if len(dirs) < 2:
        log.warning("no dataset beside BROAD: what travels between datasets is not measured")
        return
    with step("what travels"):
        run_travel(dirs, TRAVEL_DIR, travel_settings(), command)
    print((TRAVEL_DIR / "travel.md").read_text())


def sensor(broad: Path, phone: Path, command: str) -> None:
    log.info(f"sensor: models trained on all of BROAD, scored on every trial of {phone}")
    model_dir = Path("build/transfer/models_broad")
    with step("sensor"):
        run_training(load_config(), data_dir=broad, out=model_dir, verbose=True)
        phone_index = DatasetIndex.from_dir(phone)
        _write("phone", models_transfer(model_dir, phone_index), phone_index,
               f"models trained on all {len(DatasetIndex.from_dir(broad).available)} BROAD trials, on all "
               f"{len(phone_index.available)} trials of `{phone.name}`", command)


def both_datasets(broad: Path, phone: Path, store: ResultStore, backend=None) -> None:
    log.info("both datasets: the held-out study on BROAD + phone (folds by whole trial over both)")
    cfg = replace(load_study_config(), ablations=())
    with step("two-dataset study"):
        run_study(cfg, data_dir=[str(broad), str(phone)], out_dir=BOTH_DIR, store=store, backend=backend)


if __name__ == "__main__":
    setup_logging()
    sys.exit(main())
