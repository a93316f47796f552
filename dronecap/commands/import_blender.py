"""`dronecap import-blender`: a NeRF Synthetic 360° scene (Blender layout) -> dataset.h5."""

from __future__ import annotations

import argparse

HELP = "NeRF Synthetic 360 scene (transforms_*.json + RGBA PNGs) -> dataset.h5"


def add_arguments(p: argparse.ArgumentParser) -> None:
    """Options of the command."""
    p.add_argument("scene_dir", help="scene folder holding transforms_{train,val,test}.json")
    p.add_argument("-o", "--output", help="dataset to write (default: WORKDIR/dataset.h5)")
    p.add_argument(
        "--resolution", type=int, default=160, help="stored image width in pixels (default 160)"
    )
    p.add_argument(
        "--color", choices=("rgb", "gray"), default="rgb", help="stored colour (default rgb)"
    )


def run(args: argparse.Namespace) -> int:
    """Import the scene and print where it went."""
    from dronecap import workspace
    from dronecap.datasets.blender import import_blender
    from dronecap.datasets.format import open_dataset

    out = workspace.resolve(args.workdir, args.output, workspace.DATASET)
    path = import_blender(args.scene_dir, out, resolution=args.resolution, color=args.color)
    ds = open_dataset(path)
    counts = ", ".join(f"{len(ds.indices(s))} {s}" for s in ("train", "val", "test"))
    lo, hi = ds.aabb
    print(f"wrote {path}: {ds.n} views {ds.hw[1]}x{ds.hw[0]}x{ds.channels} ({counts})")
    print(f"aabb {lo.round(3).tolist()} .. {hi.round(3).tolist()} ({ds.attrs['bounds_from']})")
    return 0
