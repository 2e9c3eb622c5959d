"""``togglecf train``: learn the models and the toggling gains (``togglecf.run.train``). The parser is
``cli.parsers.add_train_parser``; this module is imported when the command runs (the ``train`` extra)."""
from __future__ import annotations

from togglecf.cli.common import backend_settings
from togglecf.cli.parsers import add_train_parser
from togglecf.run.config import load_config
from togglecf.run.pretrained import GUARD_FOLDS, retune_pretrained
from togglecf.run.train import run_training

__all__ = ["add_train_parser", "cmd_train"]


def cmd_train(args):
    cfg = load_config(args.config)
    cfg["run"].update({k: v for k, v in backend_settings(args, cfg["run"]).items() if k in cfg["run"]})
    if getattr(args, "distributed_fit", None):
        cfg["run"]["distributed_fit"] = True
    if args.guard and args.from_pretrained is None:
        raise ValueError("--guard: only with --from-pretrained (the guard checks a re-learning)")
    if args.from_pretrained is not None:  # the pretrained models kept, their settings re-learned
        retune_pretrained(cfg, data_dir=args.data, trials=args.trials, out=args.out, model=args.from_pretrained or None,
                          guard_folds=GUARD_FOLDS if args.guard else 0)
        return 0
    run_training(cfg, data_dir=args.data, trials=args.trials, out=args.out, cv=args.cv)
    return 0
