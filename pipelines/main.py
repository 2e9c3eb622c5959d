"""The README's main job (`make run`): the held-out study on every BROAD trial found.

Finds BROAD (downloading it into ./data/broad first when it is nowhere to be found, and
saying so), then runs pipelines/run_all.py: per fold, train the models and learn the gains on
the training trials, evaluate the toggling CF and all baselines on the held-out trials, and
write reports/study/ (summary.md, tables, plots).
"""
import sys
from pathlib import Path

from togglecf.core.log import setup_logging
from togglecf.data.broad import DataNotFoundError, resolve_data_dir
from togglecf.data.download import download_broad
from togglecf.run.study import load_study_config, run_study

DEFAULT_DOWNLOAD_DIR = Path("data/broad")


def data_dir() -> Path:
    try:
        return resolve_data_dir(None)
    except DataNotFoundError as exc:
        print(f"{exc}\n\nBROAD not found: downloading it into {DEFAULT_DOWNLOAD_DIR} first.", file=sys.stderr)
        return download_broad(DEFAULT_DOWNLOAD_DIR)


if __name__ == "__main__":
    setup_logging()
    run_study(load_study_config(), data_dir=data_dir(), out_dir="reports/study")
