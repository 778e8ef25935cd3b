"""``ctgpp data convert``: ScenarioNet / CommonRoad sources into the project's scene format."""

from __future__ import annotations

import argparse
from pathlib import Path

from ctgpp.data.convert import convert


def add_parsers(sub: argparse._SubParsersAction) -> None:
    data = sub.add_parser("data", help="data management")
    data_sub = data.add_subparsers(dest="data_command", required=True, metavar="ACTION")
    p = data_sub.add_parser("convert", help="convert ScenarioNet pickles or CommonRoad XML into ctgpp scenes")
    p.add_argument("src", type=Path, help="a scene file or a directory searched recursively")
    p.add_argument("dst", type=Path, help="output directory (created; its index.json is updated)")
    p.add_argument(
        "--drivable",
        type=Path,
        default=None,
        metavar="DIR",
        help="nuScenes drivable-area masks <map>.png (default: a 'drivable' folder beside SRC)",
    )
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.set_defaults(run=run_convert)


def run_convert(args: argparse.Namespace) -> int:
    if args.drivable is not None and not args.drivable.is_dir():
        raise NotADirectoryError(f"--drivable {args.drivable} is not a directory")
    report = convert(args.src, args.dst, args.drivable, progress=not args.no_progress)
    failed = [reason if str(path) in reason else f"{path}: {reason}" for path, reason in report.failed]
    if failed and not report.written:  # nothing converted: the first reason is the error
        more = f" (and {len(failed) - 1} more sources that could not be read)" if len(failed) > 1 else ""
        raise ValueError(failed[0] + more)
    print(f"converted {len(report.written)} scenes into {args.dst}")
    for note in report.notes:
        print(f"  {note}")
    for reason in failed:
        print(f"  failed: {reason}")
    if report.failed:
        print(f"{len(report.failed)} of {len(report.written) + len(report.failed)} sources could not be read")
        return 1
    return 0
