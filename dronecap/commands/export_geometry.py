"""`dronecap export-geometry`: a trained run -> mesh.ply + points.ply (marching cubes)."""

from __future__ import annotations

import argparse

HELP = "mesh (marching cubes) and coloured point cloud, as PLY, of a trained run"


def add_arguments(p: argparse.ArgumentParser) -> None:
    """Options of the command."""
    p.add_argument("run_dir", help="training run folder (holds checkpoint.pt and run.json)")
    p.add_argument("-o", "--output", help="folder to write (default: RUN_DIR/geometry)")
    p.add_argument("--dataset", help="dataset of the run (default: the one run.json names)")
    p.add_argument(
        "--resolution", type=int, default=128, help="density grid points per axis over the AABB"
    )
    p.add_argument(
        "--opacity",
        type=float,
        default=0.5,
        help="surface level: the opacity one grid step must reach (0 < opacity < 1)",
    )
    from dronecap.cpu import add_threads_argument

    add_threads_argument(p)


def run(args: argparse.Namespace) -> int:
    """Extract, write, and say what."""
    from pathlib import Path

    from dronecap.errors import InputError, check_option

    check_option("--resolution", args.resolution, 8, 1024)
    if args.threads is not None:
        check_option("--threads", args.threads, 1)
    if not 0 < args.opacity < 1:
        raise InputError(f"--opacity must be strictly between 0 and 1, got {args.opacity}")
    from dronecap.cpu import use_torch_threads
    from dronecap.nerf.geometry import extract, write_geometry
    from dronecap.nerf.run_dir import open_run

    use_torch_threads(args.threads)
    trainer, _ = open_run(args.run_dir, args.dataset)
    out = Path(args.output) if args.output else Path(args.run_dir) / "geometry"
    geo = extract(trainer, args.resolution, args.opacity)
    write_geometry(geo, out)
    print(
        f"wrote {out}/mesh.ply ({len(geo.vertices)} vertices, {len(geo.faces)} triangles) and "
        f"{out}/points.ply; surface at density {geo.level:.3g} per scene unit"
    )
    return 0
