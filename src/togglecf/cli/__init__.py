"""The ``togglecf`` command line (all argparse lives in this package)."""
from togglecf.cli.main import main

__all__ = ["main"]
