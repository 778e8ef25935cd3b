"""``ctgpp scenes`` and ``ctgpp show``: list the scenes, draw one with its vehicle numbers."""

from __future__ import annotations

import argparse
from pathlib import Path

from ctgpp.cli.common import add_data_arg, open_catalog, print_table
from ctgpp.sim.closed_loop import episode_bounds


def add_parsers(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("scenes", help="list the scenes of a data directory")
    add_data_arg(p)
    p.add_argument(
        "--split", default=None, help="only scenes of this split, e.g. mini_val (default: every split)"
    )
    p.set_defaults(run=run_scenes)

    p = sub.add_parser("show", help="draw a scene with every vehicle's number (the numbers queries use)")
    p.add_argument("scene", help="scene id, e.g. scene-0103 (a unique suffix such as 0103 works)")
    p.add_argument(
        "--start",
        type=float,
        default=None,
        metavar="SEC",
        help="time to show in seconds (default: the first episode start, 3 s, or the end of a shorter scene)",
    )
    p.add_argument(
        "--out",
        type=Path,
        default=None,
        metavar="DIR|FILE",
        help="a folder to write SCENE.png into (created if needed), or a picture file ending in .png, "
        ".jpg, .pdf or .svg (default: SCENE.png here)",
    )
    p.add_argument(
        "--radius",
        type=float,
        default=None,
        metavar="M",
        help="half-size of the view in metres (default: fitted to the vehicles)",
    )
    add_data_arg(p)
    p.set_defaults(run=run_show)


def run_scenes(args: argparse.Namespace) -> int:
    catalog = open_catalog(args)
    entries = [e for e in catalog.entries if args.split is None or e.split == args.split]
    if not entries:
        raise ValueError(f"no scenes in split {args.split!r}; splits here: {', '.join(catalog.splits())}")
    rows = [[e.id, e.map_name, f"{e.duration_s:.1f} s", e.num_vehicles, e.split] for e in entries]
    print_table(["id", "map", "duration", "vehicles logged", "split"], rows)
    print(f"\n{len(entries)} scenes in {catalog.root}")
    print("vehicles logged: every vehicle the log holds over the whole scene; a run simulates those")
    print("present at its start (`ctgpp show SCENE` draws and numbers them)")
    return 0


PICTURE_SUFFIXES = (".png", ".jpg", ".jpeg", ".pdf", ".svg")


def picture_path(out: Path | None, scene_id: str) -> Path:
    """Where ``ctgpp show --out`` writes: ``out`` itself when it names a picture file, ``out/SCENE.png``
    when it is a folder (an existing one, or a new name without a suffix: created), ``SCENE.png`` here
    without ``--out``. ValueError for anything else (an existing file or a suffix that is no picture's)."""
    name = f"{scene_id}.png"
    if out is None:
        return Path(name)
    if out.suffix.lower() in PICTURE_SUFFIXES and not out.is_dir():
        return out
    if not out.is_dir() and (out.exists() or out.suffix):
        raise ValueError(f"--out {out} is neither a folder nor a picture file: give a folder or a file "
                         f"ending in {', '.join(PICTURE_SUFFIXES)}")
    out.mkdir(parents=True, exist_ok=True)
    return out / name


def run_show(args: argparse.Namespace) -> int:
    catalog = open_catalog(args)
    scene = catalog.load(args.scene)
    first = min(episode_bounds(scene)[0], round(scene.duration_s, 6))  # a short scene: its last step
    t = first if args.start is None else args.start
    step = int(round(t / scene.dt_s))
    if not 0 <= step < scene.agents.num_steps:
        raise ValueError(f"--start {t:g} is outside {scene.id} (0-{scene.duration_s:.1f} s)")
    out = picture_path(args.out, scene.id)
    present = int((scene.agents.is_vehicle & scene.agents.valid[:, step]).sum())
    # matplotlib's drawing takes seconds: say what is drawn first
    print(f"drawing {scene.id} at {t:g} s: {present} vehicles present then (numbered), "
          f"{scene.num_vehicles} logged in the whole scene ...", flush=True)
    from ctgpp.viz import plot_scene

    plot_scene(scene, step, out, radius_m=args.radius)
    print(f"wrote {out}")
    return 0
