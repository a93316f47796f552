"""`dronecap export-transforms`: a dataset -> nerfstudio/instant-ngp transforms.json + images."""

from __future__ import annotations

import argparse

HELP = "dataset -> nerfstudio/instant-ngp transforms.json + PNG images"


def add_arguments(p: argparse.ArgumentParser) -> None:
    """Options of the command."""
    p.add_argument("input", nargs="?", help="dataset to export (default: WORKDIR/dataset.h5)")
    p.add_argument("-o", "--output", help="folder to write (default: WORKDIR/transforms)")


def run(args: argparse.Namespace) -> int:
    """Export and say where."""
    import json

    from dronecap import workspace
    from dronecap.datasets.export import export_transforms

    src = workspace.resolve(args.workdir, args.input, workspace.DATASET)
    out = workspace.resolve(args.workdir, args.output, "transforms")
    export_transforms(src, out)
    meta = json.loads((out / "transforms.json").read_text())
    print(
        f"wrote {out / 'transforms.json'}: {len(meta['frames'])} frames, images in {out / 'images'}"
    )
    return 0
