"""``ctgpp``: entry point, sub-command parsing and user-facing error handling.

Only the module of the command being run is imported (with what it needs): ``ctgpp --help``,
``ctgpp scenes``, ``ctgpp show`` and ``ctgpp rules`` start without torch. The other commands appear in
the parser by name and one-line help (``COMMANDS``) until one of them is run.
"""

from __future__ import annotations

import argparse
import logging
import os
import sys
from collections.abc import Sequence
from importlib import import_module

from ctgpp import __version__

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

# command -> (the module of ctgpp.cli that defines it, its one-line help); in the order of --help.
# The module's add_parsers gives the same help (tests/test_api.py checks).
COMMANDS: dict[str, tuple[str, str]] = {
    "scenes": ("scenes_cmd", "list the scenes of a data directory"),
    "show": ("scenes_cmd", "draw a scene with every vehicle's number (the numbers queries use)"),
    "simulate": ("simulate_cmd", "simulate a scene in closed loop (10 s, re-plan at 2 Hz)"),
    "generate": (
        "generate_cmd",
        "a scenario library: sentences × scenes × starts × seeds as ScenarioNet files with a Parquet index",
    ),
    "rules": ("rules_cmd", "list the guidance rules with their parameters, defaults and units"),
    "evaluate": (
        "evaluate_cmd",
        "closed-loop metrics of methods × rules over evaluation sets (the paper's Table 1)",
    ),
    "realism": (
        "realism_cmd",
        "the field's realism meta-metric (WOSAC): R rollouts per scenario scored against the log",
    ),
    "evaluate-queries": (
        "queries_cmd",
        "query benchmark: is each query satisfied guided vs unguided, with fail rates",
    ),
    "train": (
        "train_cmd",
        "train the CTG++ denoiser or a baseline (resumes when OUT holds a training state)",
    ),
    "data": ("data_cmd", "data management"),
    "bench": ("bench_cmd", "time guided closed-loop scenarios per sampler preset, and scaling"),
    "serve": ("serve_cmd", "the playground in the browser: pick a scene, type a sentence, watch"),
}


# commands that import torch before their first output (seconds; more on a busy machine): they say so
# in one line first
SLOW_START = ("simulate", "generate", "evaluate", "realism", "evaluate-queries", "train", "bench")


class DefaultsFormatter(argparse.HelpFormatter):
    """Help that shows every option's default: "(default: X)" is added to a help text that does not
    already say its default; flags and options without a default (None) are left as written."""

    def _get_help_string(self, action: argparse.Action) -> str:
        text = action.help or ""
        if "default" in text.lower() or action.default is None or action.default is False:
            return text
        if action.default == argparse.SUPPRESS or (isinstance(action.default, list) and not action.default):
            return text
        if not action.option_strings and action.nargs not in (argparse.OPTIONAL, argparse.ZERO_OR_MORE):
            return text
        if isinstance(action, argparse._StoreConstAction | argparse._HelpAction | argparse._VersionAction):
            return text
        return text + " (default: %(default)s)"


class Parser(argparse.ArgumentParser):
    """The parser of ``ctgpp`` and of each sub-command: defaults in every ``--help``."""

    def __init__(self, *args: object, **kwargs: object) -> None:
        kwargs.setdefault("formatter_class", DefaultsFormatter)
        super().__init__(*args, **kwargs)  # type: ignore[arg-type]


def build_parser(command: str | None = None) -> argparse.ArgumentParser:
    """The ``ctgpp`` parser, in full for ``command`` (its module imported) and by name for the others;
    ``command`` "all" builds every command in full (tests)."""
    parser = Parser(
        prog="ctgpp",
        description="Language-guided traffic simulation with scene-level diffusion (CTG++) on real logs.",
    )
    parser.add_argument("--version", action="version", version=f"ctgpp {__version__}")
    parser.add_argument("-v", "--verbose", action="store_true", help="log progress details")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND", parser_class=Parser)
    wanted = set(COMMANDS) if command == "all" else {command}
    modules = dict.fromkeys(module for name, (module, _) in COMMANDS.items() if name in wanted)
    for module in modules:
        import_module(f"ctgpp.cli.{module}").add_parsers(sub)
    for name, (_, help_text) in COMMANDS.items():
        if name not in sub.choices:
            sub.add_parser(name, help=help_text, add_help=False)
    return parser


def _command_of(argv: Sequence[str]) -> str | None:
    """The sub-command named in ``argv``: its first word that is not an option (the top-level options
    take no value)."""
    for word in argv:
        if not word.startswith("-"):
            return word if word in COMMANDS else None
    return None


def main(argv: Sequence[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    command = _command_of(argv)
    if command in SLOW_START and not {"-h", "--help"} & set(argv):
        print(f"ctgpp {command}: loading torch and the model code...", flush=True)
    parser = build_parser(command)
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
