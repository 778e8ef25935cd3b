"""Pack splits of converted data directories into one small ``.tar.xz``, to carry them to a training
machine (the device machine takes 64 MiB with the working tree; the converted INTERACTION and Waymo
scenes are about 100 MB as compressed ``.npz``).

Each scene file is rewritten uncompressed (the same arrays, so ``ctgpp`` loads it as it is), which
lets xz compress across files: the maps repeated in every scene of a location, and the zeros at the
invalid steps, cost almost nothing. ``DIR:SPLIT`` arguments; the archive holds one folder per data
directory (named as it), each with the split's scenes and an ``index.json`` of them, so
``ctgpp train --train UNPACKED/NAME:SPLIT`` reads it.

    python scripts/pack_scenes.py --out .pack/train.tar.xz /data/interaction:train /data/waymo:train
"""

from __future__ import annotations

import argparse
import json
import sys
import tarfile
import tempfile
from pathlib import Path

import numpy as np

from ctgpp.io.atomic import atomic_path


def pack(specs: list[str], out: Path) -> int:
    """Write the archive; returns the number of scenes packed."""
    count = 0
    with tempfile.TemporaryDirectory() as tmp:
        for spec in specs:
            root_text, _, split = spec.rpartition(":")
            root = Path(root_text)
            index = json.loads((root / "index.json").read_text(encoding="utf-8"))
            chosen = [e for e in index["scenes"] if e["split"] == split]
            if not chosen:
                raise SystemExit(f"pack_scenes: no scenes in split {split!r} of {root}")
            dest = Path(tmp) / root.name
            dest.mkdir(exist_ok=True)
            for entry in chosen:
                with np.load(root / entry["file"], allow_pickle=False) as z:
                    arrays = {k: z[k] for k in z.files}
                np.savez(dest / entry["file"], **arrays)  # uncompressed: xz sees the arrays
            previous = dest / "index.json"
            kept = json.loads(previous.read_text())["scenes"] if previous.exists() else []
            (dest / "index.json").write_text(json.dumps({**index, "scenes": kept + chosen}, indent=1))
            count += len(chosen)
        with atomic_path(out) as part, tarfile.open(part, "w:xz", preset=9) as tar:
            for folder in sorted(Path(tmp).iterdir()):
                tar.add(folder, arcname=folder.name)
    return count


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("specs", nargs="+", metavar="DIR:SPLIT")
    parser.add_argument("--out", type=Path, required=True, metavar="FILE.tar.xz")
    args = parser.parse_args()
    n = pack(args.specs, args.out)
    print(f"packed {n} scenes into {args.out} ({args.out.stat().st_size / 1e6:.1f} MB)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
