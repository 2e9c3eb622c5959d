"""The README's main job: evaluate on every BROAD trial found (downloading BROAD first if absent).

Run with ``make run``. Writes reports/<filter>/per_trial.csv, per_group.csv, results.json.
"""
import sys
from pathlib import Path

from togglecf.cli import main
from togglecf.data import DataNotFoundError, resolve_data_dir
from togglecf.download import download_broad

DEFAULT_DOWNLOAD_DIR = Path("data/broad")


def data_dir() -> Path:
    try:
        return resolve_data_dir(None)
    except DataNotFoundError as exc:
        print(f"{exc}\n\nBROAD not found: downloading it into {DEFAULT_DOWNLOAD_DIR} first.", file=sys.stderr)
        return download_broad(DEFAULT_DOWNLOAD_DIR)


if __name__ == "__main__":
    data = str(data_dir())
    sys.exit(main(["evaluate", "--filter", "cf", "--data", data, "--out", "reports/cf"]))
