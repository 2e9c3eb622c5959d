"""``togglecf train``: learn the models and the toggling gains (``togglecf.run.train``)."""
from __future__ import annotations

from togglecf.cli.common import DATA_HELP, add_backend_args, backend_settings
from togglecf.data.broad import SELECTION_HELP
from togglecf.run.config import DEFAULT_CONFIG, load_config
from togglecf.run.train import run_training

__all__ = ["add_train_parser"]


def add_train_parser(subparsers):
    """Register ``togglecf train`` on an argparse subparsers object."""
    sp = subparsers.add_parser("train", help="learn the motion-state classifier and noise regressors "
                               "(CV by trial, then a final fit) and save them under models/NAME")
    sp.add_argument("--config", default=str(DEFAULT_CONFIG), metavar="TOML",
                    help="pipeline settings (default: pipelines/configs/default.toml)")
    sp.add_argument("--data", metavar="DIR", action="append", default=None, help=DATA_HELP)
    sp.add_argument("--trials", metavar="LIST", help=f"{SELECTION_HELP} (default: [run] trials of the config)")
    sp.add_argument("--out", metavar="DIR", help="model directory (default: models/<run.name>)")
    sp.add_argument("--no-cv", dest="cv", action="store_false", help="skip cross-validation (final fit only)")
    add_backend_args(sp)
    sp.add_argument("--distributed-fit", action="store_true", default=None,
                    help="with --backend dask: train the final models with xgboost.dask on the workers "
                    "(also [run] distributed_fit)")
    sp.set_defaults(func=cmd_train)
    return sp


def cmd_train(args):
    cfg = load_config(args.config)
    cfg["run"].update({k: v for k, v in backend_settings(args, cfg["run"]).items() if k in cfg["run"]})
    if getattr(args, "distributed_fit", None):
        cfg["run"]["distributed_fit"] = True
    run_training(cfg, data_dir=args.data, trials=args.trials, out=args.out, cv=args.cv)
    return 0
