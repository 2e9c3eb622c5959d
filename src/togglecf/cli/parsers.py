"""Every ``togglecf`` subcommand's argparse parser, and nothing heavy: building them imports no
filter, no numba code and no optional dependency, so ``togglecf --help`` is fast and works with
``pip install togglecf`` alone. A subcommand's implementation (``togglecf.cli.<module>``) is
imported when it runs (``Run``), after a check that the extras it needs are installed
(``togglecf.core.extras``); the filter names a command accepts are read from the registry when an
argument is checked or the command's ``--help`` lists them (``LazyChoices``)."""
from __future__ import annotations

import argparse
from contextlib import nullcontext
from importlib import import_module

from togglecf import __version__
from togglecf.cli.common import DATA_HELP, add_backend_args, add_data_args
from togglecf.cli.library_noise import library_noise_filtered
from togglecf.core.config import config_path
from togglecf.core.extras import check_extra
from togglecf.data.broad import SELECTION_HELP

__all__ = ["DESCRIPTION", "Run", "LazyChoices", "build_parser", "add_train_parser", "add_plot_parser",
           "add_stream_parser", "add_export_parser", "add_prune_parser", "add_sweep_arguments", "add_import_parser"]

DESCRIPTION = ("togglecf: orientation filters on BROAD (evaluate, tune), the learning pipeline (train), views "
               "(plot), live orientation (stream), embedded C code (export), data (trials, download, import).")


class Run:
    """``args.func`` of a subcommand: ``Run("train", "togglecf.cli.train:cmd_train", extras=("train",))``
    imports ``togglecf.cli.train`` only when called, after ``check_extra`` of each extra (a missing one:
    ``MissingExtraError``, one line naming it, before any work). ``quiet_libraries``: the tree libraries'
    version and deprecation chatter is dropped while it runs (``cli.library_noise``)."""

    def __init__(self, command: str, target: str, extras: tuple = (), quiet_libraries: bool = False):
        self.command, self.target, self.extras = command, target, tuple(extras)
        self.quiet_libraries = quiet_libraries

    def __call__(self, args):
        for extra in self.extras:
            check_extra(extra, what=f"togglecf {self.command}")
        module, _, name = self.target.partition(":")
        with library_noise_filtered() if self.quiet_libraries else nullcontext():
            return getattr(import_module(module), name)(args)

    def __repr__(self):
        return f"Run({self.command!r}, {self.target!r}, extras={self.extras!r})"


class LazyChoices:
    """argparse ``choices`` read from ``module.attr`` on first use (a value checked, a command's
    ``--help``), not when the parser is built. Give the argument a ``metavar`` (argparse would list
    the choices at once otherwise) and ``%(choices)s`` in its help."""

    def __init__(self, module: str, attr: str, sort: bool = False):
        self.module, self.attr, self.sort = module, attr, sort
        self._values = None

    def values(self) -> tuple:
        if self._values is None:
            v = getattr(import_module(self.module), self.attr)
            self._values = tuple(sorted(v) if self.sort else v)
        return self._values

    def __contains__(self, item):
        return item in self.values()

    def __iter__(self):
        return iter(self.values())

    def __len__(self):
        return len(self.values())

    def __str__(self):  # "%(names)s" in a help (``names_in_help``)
        return ", ".join(map(str, self.values()))


#: every filter name a command accepts, the trained ones included (``togglecf.registry.FILTER_NAMES``, the
#: names of the filter table ``CATALOG``)
FILTER_CHOICES = LazyChoices("togglecf.registry", "FILTER_NAMES")
#: the classic filters of the same table (``togglecf.registry.CLASSIC_NAMES``): the ones ``tune`` searches
CLASSIC_CHOICES = LazyChoices("togglecf.registry", "CLASSIC_NAMES")
#: the trained filters of the same table (``togglecf.registry.TRAINED``): the ones ``export`` writes in C
TRAINED_CHOICES = LazyChoices("togglecf.registry", "TRAINED")


def names_in_help(action, names: LazyChoices):
    """Lets the help of ``action`` (an argument without ``choices``, e.g. a comma-separated list) say
    ``%(names)s``: argparse fills a help from the action's attributes when the help is shown."""
    action.names = names
    return action


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="togglecf", description=DESCRIPTION)
    p.add_argument("--version", action="version", version=f"togglecf {__version__}")
    sub = p.add_subparsers(dest="command")

    def sweep_args(sp):
        add_backend_args(sp, config=True)
        sp.add_argument("--chunk-size", type=int, default=None, metavar="N",
                        help="parameter sets per task (default: one task per trial locally, automatic on Dask)")
        sp.add_argument("--no-resume", dest="resume", action="store_false",
                        help="with --out: recompute everything instead of reusing DIR/sweep.jsonl")

    sp = sub.add_parser("trials", help="list the BROAD trials found and those missing")
    add_data_args(sp)
    sp.set_defaults(func=Run("trials", "togglecf.cli.data:cmd_trials"))

    sp = sub.add_parser("evaluate", help="run a filter (or several) on BROAD trials and print BROAD's error table")
    add_data_args(sp)
    which = sp.add_mutually_exclusive_group()
    which.add_argument("--filter", default="learned_vqf", choices=FILTER_CHOICES, metavar="NAME",
                       help="one of %(choices)s (default: learned_vqf, the pretrained learned VQF the package "
                       "ships; vqf: the reference VQF, the [vqf] extra)")
    names_in_help(which.add_argument(
        "--filters", metavar="LIST", help="several filters in one run, comma-separated, e.g. "
        "learned_vqf,vqf,madgwick: one table, a row per filter (mean total/heading/inclination RMSE, per-group "
        "totals); each at its defaults (no --param); toggling / vqf_toggling take --models; any of %(names)s"),
        FILTER_CHOICES)
    sp.add_argument("--param", action="append", default=[], metavar="NAME=VALUE",
                    help="setting of the --filter, repeatable (default: the filter's documented defaults)")
    sp.add_argument("--models", metavar="DIR|FILE", help="toggling / vqf_toggling: a `togglecf train` model "
                    "directory (models + learned gains); learned_vqf: a portable model FILE.npz (from `togglecf train "
                    "--from-pretrained`) instead of the shipped one (default: none)")
    sp.add_argument("--6d", dest="six_d", action="store_true", help="ignore the magnetometer (heading offset removed)")
    sp.add_argument("--out", metavar="DIR", help="write per_trial.csv, per_group.csv and results.json here "
                    "(--filters: those of each filter in DIR/<filter>/, the table in DIR/summary.csv)")
    sp.add_argument("--jobs", type=int, default=None, help="worker processes (default: all cores)")
    sweep_args(sp)
    sp.set_defaults(func=Run("evaluate", "togglecf.cli.evaluate:cmd_evaluate", extras=("data",)))

    sp = sub.add_parser("tune", help="grid search; report BROAD's TAGP (lowest mean total RMSE)")
    add_data_args(sp)
    sp.add_argument("--filter", required=True, choices=CLASSIC_CHOICES, metavar="NAME", help="one of %(choices)s")
    sp.add_argument("--grid", action="append", required=True, metavar="NAME=START:STOP:STEP",
                    help="parameter grid, repeatable; also NAME=a,b,c")
    sp.add_argument("--6d", dest="six_d", action="store_true")
    sp.add_argument("--out", metavar="DIR", help="write the tables here; results stream to DIR/sweep.jsonl as "
                    "they arrive and a rerun with the same --out computes only the missing points")
    sp.add_argument("--jobs", type=int, default=None, help="local backend: worker processes (default: all cores)")
    sweep_args(sp)
    sp.set_defaults(func=Run("tune", "togglecf.cli.evaluate:cmd_tune", extras=("data",)))

    add_train_parser(sub)
    add_plot_parser(sub)
    add_stream_parser(sub)
    add_export_parser(sub)
    add_prune_parser(sub)

    sp = sub.add_parser("download", help="fetch BROAD (trial files + trials.json) from GitHub")
    sp.add_argument("dest", nargs="?", default="data/broad", help="target directory (default: ./data/broad)")
    sp.add_argument("--url", default=None, help="archive URL (default: BROAD's GitHub main branch zip)")
    sp.add_argument("--format", choices=("hdf5", "mat", "both"), default="hdf5")
    sp.set_defaults(func=Run("download", "togglecf.cli.data:cmd_download"))
    add_import_parser(sub)
    return p


def add_import_parser(subparsers):
    """``togglecf import``: a CSV/NumPy log (and a mocap reference) into BROAD's layout."""
    sp = subparsers.add_parser("import", help="turn a CSV/NumPy IMU log (and a mocap reference: synchronised and "
                               "aligned with qmt) into a trial in BROAD's layout that evaluate reads")
    sp.add_argument("imu", metavar="IMU", help="IMU log: .csv with a header (t, gyr_x..z, acc_x..z, mag_x..z; optional "
                    "q0..q3, pos_x..z, movement), .npz or .npy (docs/guide/import.md)")
    sp.add_argument("--reference", metavar="MOCAP", help="reference log on its own clock (t, q0..q3, optional "
                    "pos_x..z): resampled, clock offset and drift, IMU-to-marker rotation and frame found with qmt "
                    "(the [import] extra)")
    sp.add_argument("--out", required=True, metavar="DIR", help="data directory: NAME.hdf5, trials.json (updated), "
                    "NAME.import.json (the report), NAME.import.png (residuals, with --reference and matplotlib)")
    sp.add_argument("--name", help="trial name (default: the IMU log's file name without its suffix)")
    sp.add_argument("--group", action="append", metavar="G", help="group in trials.json, repeatable "
                    "(default: imported)")
    sp.add_argument("--units", metavar="SPEC", help="the logs' units, e.g. gyr=dps,acc=g,mag=uT (gyr: rad/s|dps; "
                    "acc: m/s2|g|mg; mag: uT|gauss|mT|nT; default rad/s, m/s2, uT)")
    sp.add_argument("--time-unit", choices=LazyChoices("togglecf.core.units", "TIME_UNITS", sort=True), metavar="UNIT",
                    default="s", help="unit of the t columns: one of %(choices)s (default: s)")
    sp.add_argument("--frame", choices=("enu", "ned"), default="enu",
                    help="earth frame of the reference quaternions and positions (default: enu)")
    sp.add_argument("--quat-order", choices=("wxyz", "xyzw"), default="wxyz", help="order of q0..q3 (default: wxyz)")
    sp.add_argument("--calibrate-mag", action="store_true", help="with --reference: remove hard and soft iron "
                    "(qmt.calibrateMagnetometerSimple; slow rotations in all directions, away from iron)")
    sp.add_argument("--thorough", action="store_true", help="with --reference: qmt's full searches as BROAD was "
                    "made (24 mountings: an IMU at any angle to the markers; many minutes); default: one start each, "
                    "seconds")
    sp.add_argument("--no-plot", dest="plot", action="store_false", help="no residual plot")
    sp.set_defaults(func=Run("import", "togglecf.cli.importer:cmd_import"))
    return sp


def add_train_parser(subparsers):
    """Register ``togglecf train`` on an argparse subparsers object."""
    sp = subparsers.add_parser("train", help="learn the motion-state classifier and noise regressors "
                               "(CV by trial, then a final fit) and save them under models/NAME")
    sp.add_argument("--config", default=str(config_path("default.toml")), metavar="TOML",
                    help="pipeline settings (default: the package's togglecf/configs/default.toml)")
    sp.add_argument("--data", metavar="DIR", action="append", default=None, help=DATA_HELP)
    sp.add_argument("--trials", metavar="LIST", help=f"{SELECTION_HELP} (default: [run] trials of the config)")
    sp.add_argument("--out", metavar="DIR", help="model directory (default: models/<run.name>)")
    sp.add_argument("--no-cv", dest="cv", action="store_false", help="skip cross-validation (final fit only)")
    sp.add_argument("--from-pretrained", nargs="?", const="", default=None, metavar="FILE",
                    help="keep the pretrained learned VQF's models (or those of the portable model FILE) and "
                    "re-learn only its settings (9D and 6D, [gains.vqf] of the config) on the selected trials: "
                    "minutes; writes OUT/learned_vqf.npz (default OUT: models/<run.name>-retuned), which "
                    "--filter learned_vqf --models FILE runs (default: off, train everything)")
    sp.add_argument("--guard", action="store_true",
                    help="with --from-pretrained: check the re-learning on recordings it was not learned on (re-learn "
                    "on 2/3 of the trials, score the rest, 3 times) and keep a mode's settings only where they beat the "
                    "VQF core there by one standard error; else the core runs (default: off)")
    add_backend_args(sp)
    sp.add_argument("--distributed-fit", action="store_true", default=None,
                    help="with --backend dask: train the final models with xgboost.dask on the workers "
                    "(also [run] distributed_fit)")
    sp.set_defaults(func=Run("train", "togglecf.cli.train:cmd_train", extras=("train",)))
    return sp


def _filters_arg(sp, default: str) -> None:
    """``--filters`` of a plot: comma-separated filter names, ``default`` shown in the help."""
    names_in_help(sp.add_argument("--filters", default=default, help=f"comma-separated filter names (default: "
                                  f"{default}; learned_vqf: the pretrained learned VQF); any of %(names)s; --models "
                                  "adds toggling"), FILTER_CHOICES)


def add_plot_parser(subparsers):
    """``togglecf plot euler|error|3d ...``."""
    p = subparsers.add_parser("plot", help="plot filters' orientation on one trial (Euler angles and their errors, "
                              "BROAD's errors over time, 3-D)")
    psub = p.add_subparsers(dest="plot_kind", required=True)

    def common(sp):
        sp.add_argument("--trial", required=True, help="one trial number or name, e.g. 05; with several --data, "
                        "<dir name>/<trial> (e.g. tyrex_nexus5/Jakob_Nexus5_Dist_AR) when the name alone matches "
                        "trials of several directories")
        sp.add_argument("--data", metavar="DIR", action="append", default=None, help=DATA_HELP)
        sp.add_argument("--models", metavar="DIR|FILE", help="model directory for the toggling filter, or a "
                        "portable model FILE.npz for learned_vqf (from `togglecf train --from-pretrained`; default: "
                        "the shipped model)")
        sp.add_argument("--6d", dest="six_d", action="store_true", help="ignore the magnetometer")
        sp.add_argument("--start", type=float, default=0.0, help="start time [s]")
        sp.add_argument("--end", type=float, default=None, help="end time [s] (default: trial end)")
        sp.add_argument("--out", required=True, metavar="FILE")

    def run(kind):
        return Run("plot", f"togglecf.cli.plot:cmd_plot_{kind}", extras=("plot",))

    sp = psub.add_parser("euler", help="roll/pitch/yaw of estimates vs ground truth, and estimate − truth per "
                         "angle (wrapped to ±180°) -> PNG/SVG")
    common(sp)
    _filters_arg(sp, "learned_vqf")
    sp.set_defaults(func=run("euler"))

    sp = psub.add_parser("error", help="BROAD's total/heading/inclination error over time of several filters "
                         "-> PNG/SVG")
    common(sp)
    _filters_arg(sp, "learned_vqf,vqf_core")
    sp.set_defaults(func=run("error"))

    sp = psub.add_parser("3d", help="IMU box of an estimate beside the truth: .gif/.mp4 animation or .png frames")
    common(sp)
    sp.add_argument("--filter", default="learned_vqf", choices=FILTER_CHOICES, metavar="NAME",
                    help="one of %(choices)s (default: learned_vqf, the pretrained learned VQF)")
    sp.add_argument("--fps", type=int, default=10)
    sp.add_argument("--duration", type=float, default=None, help="animation length [s] (default: min(8, span); "
                    "the trial or --start/--end span is subsampled to fps*duration frames)")
    sp.add_argument("--frames", type=int, default=8, help="number of key frames for a still image")
    sp.set_defaults(func=run("3d"))
    return p


def add_stream_parser(subparsers):
    """``togglecf stream ...``."""
    sp = subparsers.add_parser("stream", help="live orientation from a serial IMU (or a CSV file / stdin)",
                               formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    src = sp.add_mutually_exclusive_group(required=True)
    src.add_argument("--port", metavar="DEVICE", help="serial port, e.g. /dev/ttyUSB0 or COM3 (the [stream] extra)")
    src.add_argument("--input", metavar="FILE", help="read lines from a file, or - for stdin")
    sp.add_argument("--baud", type=int, default=115200)
    sp.add_argument("--filter", default="learned_vqf", choices=FILTER_CHOICES, metavar="NAME",
                    help="one of %(choices)s (learned_vqf: the pretrained learned VQF)")
    sp.add_argument("--models", metavar="DIR|FILE", help="model directory for --filter toggling / vqf_toggling; "
                    "a portable model FILE.npz for --filter learned_vqf (from `togglecf train --from-pretrained`; "
                    "none: the shipped model)")
    sp.add_argument("--units", default="gyr=rad/s,acc=m/s2,mag=uT",
                    help="input units, e.g. gyr=dps,acc=g,mag=uT (gyr: rad/s|dps; acc: m/s2|g|mg; "
                    "mag: uT|nT|G|mG); converted to rad/s, m/s², µT")
    sp.add_argument("--time-unit", choices=LazyChoices("togglecf.core.units", "TIME_UNITS", sort=True),
                    metavar="UNIT", default="s", help="unit of the timestamp t: one of %(choices)s")
    sp.add_argument("--unit-check", type=float, default=2.0, metavar="SECONDS",
                    help="check the units on the first SECONDS of samples (held back, then filtered): a field "
                    "another unit explains (gyr in °/s, acc in g or mg, mag in gauss, mT or nT) stops the stream "
                    "with one line naming the --units that fixes it; 0: no check")
    # required: every time constant is converted at this rate, and a wrong guess (BROAD's 285.714 Hz for a
    # 100-Hz sensor) silently scales them all
    sp.add_argument("--fs", type=float, required=True,
                    help="the sensor's nominal sampling rate [Hz] (coefficients, gap detection, first Δt)")
    sp.add_argument("--rate", type=float, default=10.0, help="output lines per second of stream time (0: every sample)")
    sp.add_argument("--6d", dest="six_d", action="store_true", help="lines without magnetometer: t,gx,gy,gz,ax,ay,az")
    sp.add_argument("--max-gap", type=float, default=1.0, help="Δt [s] above which the time base restarts")
    sp.add_argument("--retry", type=float, default=1.0, help="seconds between serial reconnect attempts")
    sp.add_argument("--precision", type=int, default=6, help="decimals printed")
    sp.set_defaults(func=Run("stream", "togglecf.cli.stream:cmd_stream"))
    return sp


def add_sweep_arguments(sp):
    """The grid and protocol options shared by ``togglecf prune`` and ``togglecf export --max-bytes``
    (both also have ``--models``, ``--data`` and ``--no-riscv``)."""
    sp.add_argument("--trees", default="10,20,30", metavar="LIST", help="trees per booster (default: 10,20,30)")
    sp.add_argument("--depths", default="3,4", metavar="LIST", help="tree depths (default: 3,4)")
    sp.add_argument("--features", default="0,24,12", metavar="LIST",
                    help="number of most important features the trees may use, 0 = all (default: 0,24,12)")
    sp.add_argument("--folds", type=int, default=5, help="held-out folds by whole trial (default: 5, as the study)")
    sp.add_argument("--inner-folds", type=int, default=3, help="CV folds inside each training set, whose "
                    "out-of-fold predictions the gains are learned on (default: 3, as the study)")
    add_backend_args(sp)  # dask: every (point, fold) a task; the sweep directory must be shared with the workers


def add_export_parser(subparsers):
    """``togglecf export``: register on the CLI's subparsers (sets ``func``)."""
    sp = subparsers.add_parser("export", help="export a model directory as C code (TL2cgen or compact arrays), "
                               "checked against the Python models, with object sizes")
    sp.add_argument("--models", metavar="DIR|FILE", help="a `togglecf train` model directory, or with --filter "
                    "vqf_toggling a portable model FILE.npz (from `togglecf train --from-pretrained`); default: "
                    "with --filter vqf_toggling the pretrained learned VQF the package ships (the C filter alone: "
                    "its trees are already compiled), else required")
    sp.add_argument("--out", required=True, metavar="DIR", help="output directory, e.g. build/embedded/NAME")
    sp.add_argument("--format", choices=("tl2cgen", "array", "both"), default="both")
    sp.add_argument("--quantize", action="store_true", help="TL2cgen: quantized thresholds (integer compares)")
    sp.add_argument("--data", metavar="DIR", help="BROAD directory for the equivalence check")
    sp.add_argument("--trials", metavar="LIST", default="all",
                    help="trials whose windows are checked (default: all present)")
    sp.add_argument("--no-check", action="store_true", help="skip the equivalence check (no data needed)")
    sp.add_argument("--no-riscv", action="store_true", help="host sizes only")
    sp.add_argument("--6d", dest="six_d", action="store_true",
                    help="C filter without magnetometer (6D gains from gains.json)")
    sp.add_argument("--filter", choices=TRAINED_CHOICES, default="toggling", metavar="NAME",
                    help="which learned filter (one of %(choices)s) goes to OUT/filter in C: toggling (the toggling CF, gains 9d/6d; "
                    "togglecf.embedded.cfilter) or vqf_toggling (the VQF core with learned time constants, gains "
                    "vqf_9d/vqf_6d; togglecf.embedded.cvqf_toggling: sizes for host, rv32imc and Cortex-M4F)")
    sp.add_argument("--forest-layout", choices=("array", "complete"), default="array",  # forest_export.C_LAYOUTS
                    help="C layout of the filter's trees (--filter): array (default; compact, the faster walk on a "
                    "microcontroller) or complete (padded to complete trees, no branch on the data per node: the "
                    "faster walk on a processor that predicts branches, e.g. a PC or a Cortex-A; same margins)")
    sp.add_argument("--max-bytes", type=int, metavar="N",
                    help="flash budget: train a pruned point on the model's training trials into OUT/models and "
                    "export that: the point of an existing pruning sweep in --sweep DIR with the lowest held-out "
                    "error whose RISC-V object code (array format; tl2cgen with --format tl2cgen) fits in N bytes, "
                    "else the default point (togglecf.run.prune.DEFAULT_EXPORT_POINT, all features); minutes")
    sp.add_argument("--full-sweep", action="store_true",
                    help="with --max-bytes: run (or resume) the pruning sweep of --models in --sweep DIR first "
                    "(its points x 5 folds on the model's training trials: the longest step of an export) and pick from it")
    sp.add_argument("--sweep", metavar="DIR", help="sweep directory for --max-bytes (default: OUT/sweep)")
    add_sweep_arguments(sp)
    sp.set_defaults(func=Run("export", "togglecf.cli.export:cmd_export", extras=("export",), quiet_libraries=True))
    return sp


def add_prune_parser(subparsers):
    sp = subparsers.add_parser("prune", help="pruning sweep: model size against the toggling filter's held-out "
                               "BROAD error; Pareto front as CSV and plot")
    sp.add_argument("--models", required=True, metavar="DIR", help="the `togglecf train` model directory to prune "
                    "(its config, training trials and gain search are kept; only model sizes change)")
    sp.add_argument("--out", required=True, metavar="DIR", help="sweep directory (resumable: finished points "
                    "are kept in DIR/sweep_rows.jsonl)")
    sp.add_argument("--max-bytes", type=int, metavar="N", help="mark this budget and name the best point within it")
    sp.add_argument("--format", choices=LazyChoices("togglecf.run.prune", "SIZE_KEYS"), metavar="FORMAT",
                    default="array", help="code format whose RISC-V object size is the size axis: one of "
                    "%(choices)s (default: array)")
    add_sweep_arguments(sp)
    sp.add_argument("--data", metavar="DIR", action="append", default=None,
                    help="data directory, repeatable (default: the directories the models were trained on when "
                    "they were several, else the default location)")
    sp.add_argument("--no-riscv", action="store_true", help="host sizes only")
    sp.set_defaults(func=Run("prune", "togglecf.cli.prune:cmd_prune", extras=("export", "plot"),
                             quiet_libraries=True))
    return sp
