"""`dronecap import-colmap`: a COLMAP sparse model + its images folder -> dataset.h5."""

from __future__ import annotations

import argparse

HELP = "COLMAP sparse model (sparse/0) + images folder -> dataset.h5"


def add_arguments(p: argparse.ArgumentParser) -> None:
    """Options of the command."""
    p.add_argument("model", help="COLMAP model folder (cameras/images/points3D .bin or .txt)")
    p.add_argument("images", help="folder the model's image names are relative to")
    from dronecap.commands.import_transforms import add_import_options

    add_import_options(p)


def run(args: argparse.Namespace) -> int:
    """Import and print what was stored."""
    from dronecap import workspace
    from dronecap.datasets.import_colmap import import_colmap
    from dronecap.datasets.import_scene import check_options, describe

    check_options(args.size, args.color)
    out = workspace.resolve(args.workdir, args.output, workspace.DATASET)
    path = import_colmap(args.model, args.images, out, size=args.size, color=args.color)
    print(describe(path))
    return 0
