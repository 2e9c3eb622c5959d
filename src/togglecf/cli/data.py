"""``togglecf trials`` (the trials found and those missing) and ``togglecf download`` (BROAD from GitHub)."""
from __future__ import annotations

from togglecf.cli.common import data_index
from togglecf.core.extras import check_extra
from togglecf.data.download import download_broad

__all__ = ["cmd_trials", "cmd_download"]


def cmd_trials(args):
    index = data_index(args)
    for name in index.select(args.trials):
        print(f"{name:45s} {index.available[name].name}")


def cmd_download(args):
    if args.format != "mat":  # the downloaded .hdf5 files are verified by reading them
        check_extra("data", what=f"togglecf download --format {args.format}")
    kwargs = {"fmt": args.format}
    if args.url:
        kwargs["url"] = args.url
    dest = download_broad(args.dest, **kwargs)
    print(f"BROAD is in {dest}; use it with --data {dest} (or TOGGLECF_DATA={dest})")
