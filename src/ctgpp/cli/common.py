"""Arguments and helpers shared by several sub-commands."""

from __future__ import annotations

import argparse
from pathlib import Path

from ctgpp.data.catalog import Catalog


def add_data_arg(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--data",
        type=Path,
        default=None,
        metavar="DIR",
        help="directory of converted scenes (default: the embedded nuScenes v1.0-mini scenes)",
    )


def open_catalog(args: argparse.Namespace) -> Catalog:
    return Catalog.open(args.data)


def print_table(header: list[str], rows: list[list[object]]) -> None:
    """A plain aligned text table on stdout."""
    cells = [header] + [[_fmt(c) for c in row] for row in rows]
    widths = [max(len(r[i]) for r in cells) for i in range(len(header))]
    for k, row in enumerate(cells):
        print("  ".join(c.ljust(w) for c, w in zip(row, widths, strict=True)).rstrip())
        if k == 0:
            print("  ".join("-" * w for w in widths))


def _fmt(value: object) -> str:
    if isinstance(value, float):
        return f"{value:.3f}" if value == value else "-"
    return str(value)
