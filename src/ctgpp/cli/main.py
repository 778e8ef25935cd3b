"""``ctgpp``: entry point, sub-command parsing and user-facing error handling."""

from __future__ import annotations

import argparse
import logging
import os
import sys
from collections.abc import Sequence

from ctgpp import __version__
from ctgpp.cli import (
    bench_cmd,
    data_cmd,
    evaluate_cmd,
    queries_cmd,
    rules_cmd,
    scenes_cmd,
    simulate_cmd,
    train_cmd,
)

# Mistakes a user can make (bad paths, ids, times, files): reported in one line, exit code 2.
USER_ERRORS = (
    FileNotFoundError,
    FileExistsError,
    NotADirectoryError,
    IsADirectoryError,
    PermissionError,
    ValueError,
    KeyError,
)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="ctgpp",
        description="Language-guided traffic simulation with scene-level diffusion (CTG++) on real logs.",
    )
    parser.add_argument("--version", action="version", version=f"ctgpp {__version__}")
    parser.add_argument("-v", "--verbose", action="store_true", help="log progress details")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    commands = (scenes_cmd, simulate_cmd, rules_cmd, evaluate_cmd, queries_cmd, train_cmd, data_cmd)
    for module in (*commands, bench_cmd):
        module.add_parsers(sub)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    logging.basicConfig(
        level=logging.INFO if args.verbose else logging.WARNING, format="%(levelname)s: %(message)s"
    )
    try:
        return int(args.run(args) or 0)
    except USER_ERRORS as err:
        if os.environ.get("CTGPP_DEBUG"):
            raise
        message = err.args[0] if isinstance(err, KeyError) and err.args else err
        print(f"ctgpp: error: {message}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("ctgpp: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
