"""`dronecap split`: train/test split of a posed flight -> dataset.h5."""

from __future__ import annotations

import argparse

HELP = "train/test split of a posed flight (every k-th frame to test) -> dataset.h5"


def add_arguments(p: argparse.ArgumentParser) -> None:
    """Options of the command."""
    p.add_argument("input", nargs="?", help="posed flight (default: WORKDIR/posed.h5)")
    p.add_argument("-o", "--output", help="dataset to write (default: WORKDIR/dataset.h5)")
    p.add_argument(
        "--every", type=int, default=8, help="hold out one frame in EVERY for test (default 8)"
    )


def run(args: argparse.Namespace) -> int:
    """Split and print the counts."""
    from dronecap import workspace
    from dronecap.datasets.format import open_dataset
    from dronecap.datasets.split import split_dataset
    from dronecap.errors import check_option

    check_option("--every", args.every, minimum=2)
    src = workspace.resolve(args.workdir, args.input, workspace.POSED)
    out = workspace.resolve(args.workdir, args.output, workspace.DATASET)
    ds = open_dataset(split_dataset(src, out, every=args.every))
    counts = ", ".join(f"{len(ds.indices(s))} {s}" for s in ("train", "val", "test"))
    how = (
        "kept the input's split" if ds.provenance["params"]["kept_existing_split"] else "new split"
    )
    print(f"wrote {out}: {ds.n} frames ({counts}; {how})")
    return 0
