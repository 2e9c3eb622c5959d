"""togglecf: orientation filters on BROAD (evaluate, tune), the learning pipeline (train), views (plot),
live orientation (stream), embedded C code (export), data (trials, download).

``main`` builds the parsers (``cli.parsers``: cheap, no filter or optional dependency imported) and
runs the chosen subcommand, whose implementation is imported only then. Errors in the input and a
missing extra (``togglecf.core.extras``) are one line on stderr, never a traceback."""
from __future__ import annotations

import sys

from togglecf.cli.parsers import build_parser
from togglecf.core.extras import MissingExtraError
from togglecf.core.log import setup_logging

__all__ = ["main"]


def main(argv=None) -> int:
    setup_logging()
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
    except MissingExtraError as exc:  # a command's --help listing names from a module that needs an extra
        print(exc, file=sys.stderr)
        return 1
    if not hasattr(args, "func"):
        parser.print_help()
        return 2
    try:
        return args.func(args) or 0
    except MissingExtraError as exc:
        print(exc, file=sys.stderr)
        return 1
    # DataError is a ValueError, DataNotFoundError a FileNotFoundError (togglecf.data.broad)
    except (FileNotFoundError, ValueError, KeyError, TypeError) as exc:
        msg = exc.args[0] if isinstance(exc, KeyError) and exc.args else exc
        print(f"togglecf {args.command}: error: {msg}", file=sys.stderr)
        return 1


if __name__ == "__main__":
    sys.exit(main())
