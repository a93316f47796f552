"""`dronecap import-transforms`: an instant-ngp / nerfstudio dataset -> dataset.h5."""

from __future__ import annotations

import argparse

HELP = "instant-ngp / nerfstudio transforms.json dataset (folder or .json) -> dataset.h5"


def add_arguments(p: argparse.ArgumentParser) -> None:
    """Options of the command."""
    p.add_argument(
        "source",
        help="folder with transforms.json or transforms_{train,val,test}.json, or a .json file",
    )
    add_import_options(p)


def add_import_options(p: argparse.ArgumentParser) -> None:
    """The options every scene importer shares: output, stored width, colour."""
    p.add_argument("-o", "--output", help="dataset to write (default: WORKDIR/dataset.h5)")
    p.add_argument("--size", type=int, default=160, help="stored image width in pixels")
    p.add_argument(
        "--color",
        choices=("auto", "rgb", "gray"),
        default="auto",
        help="stored colour; auto: gray when every image is gray",
    )


def run(args: argparse.Namespace) -> int:
    """Import and print what was stored."""
    from dronecap import workspace
    from dronecap.datasets.import_scene import check_options, describe
    from dronecap.datasets.import_transforms import import_transforms

    check_options(args.size, args.color)
    out = workspace.resolve(args.workdir, args.output, workspace.DATASET)
    print(describe(import_transforms(args.source, out, size=args.size, color=args.color)))
    return 0
