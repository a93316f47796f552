"""`dronecap shard`: IID or viewpoint-sector shards of a dataset, one file per drone -> shards/."""

from __future__ import annotations

import argparse

HELP = "IID or viewpoint-sector shards of a dataset's train images, one file per drone -> shards/"


def add_arguments(p: argparse.ArgumentParser) -> None:
    """Options of the command."""
    p.add_argument("input", nargs="?", help="dataset to shard (default: WORKDIR/dataset.h5)")
    p.add_argument("-o", "--output", help="folder to write (default: WORKDIR/shards)")
    p.add_argument("--clients", type=int, default=4, help="number of drones K (default 4)")
    p.add_argument(
        "--scheme",
        default="sector",
        help="iid (seeded shuffle) or sector (contiguous viewpoint sectors; default)",
    )
    p.add_argument("--seed", type=int, default=0, help="seed of the iid shuffle, >= 0 (default 0)")


def run(args: argparse.Namespace) -> int:
    """Shard and print one line per drone."""
    import json

    from dronecap import workspace
    from dronecap.datasets.shard import SCHEMES, shard_dataset
    from dronecap.errors import InputError, check_option

    check_option("--clients", args.clients, minimum=1)
    check_option("--seed", args.seed, minimum=0)
    if args.scheme not in SCHEMES:
        raise InputError(f"--scheme must be one of {', '.join(SCHEMES)}, got {args.scheme!r}")
    src = workspace.resolve(args.workdir, args.input, workspace.DATASET)
    out = workspace.resolve(args.workdir, args.output, workspace.SHARDS)
    shard_dataset(src, out, clients=args.clients, scheme=args.scheme, seed=args.seed)
    summary = json.loads((out / "summary.json").read_text())
    print(f"wrote {out}: {args.scheme} shards, {len(summary['test_views'])} common test views")
    for s in summary["shards"]:
        sector = ""
        if "azimuth_deg" in s:
            a, b = s["azimuth_deg"]
            sector = f", azimuth {a:.0f}..{b:.0f} deg ({s['span_deg']:.0f} deg)"
        print(f"  {s['file']}: {s['n_train']} train views{sector}")
    return 0
