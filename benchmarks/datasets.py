"""Datasets benchmark: import, carving grid (time vs tightness), HDF5 reads, sharding, export.

Run: ``nice .venv/bin/python benchmarks/datasets.py`` (needs ../shared/data/nerf_synthetic_160).
Prints a table and writes it to ``benchmarks/results/datasets.md``, and a top view of lego's
sector shards to ``benchmarks/results/datasets_sectors.png``. Times are medians of
``REPEAT`` runs on this machine (2 shared cores: noisy).
"""

from __future__ import annotations

import json
import shutil
import sys
import tempfile
from pathlib import Path

import cv2
import h5py
import numpy as np
from _runs import median_seconds

from dronecap.datasets.blender import import_blender
from dronecap.datasets.bounds import carve_aabb, lookat_cube
from dronecap.datasets.export import export_transforms
from dronecap.datasets.format import open_dataset
from dronecap.datasets.shard import azimuths, shard_dataset

REPO = Path(__file__).resolve().parents[1]
LEGO = REPO.parent / "shared" / "data" / "nerf_synthetic_160" / "lego"
OUT = REPO / "benchmarks" / "results" / "datasets.md"
REPEAT = 3


def upsampled_scene(root: Path, size: int) -> Path:
    """lego's train split with its PNGs upsampled to ``size`` px (exercises the resize path)."""
    (root / "train").mkdir(parents=True)
    shutil.copy(LEGO / "transforms_train.json", root)
    for png in (LEGO / "train").glob("*.png"):
        im = cv2.imread(str(png), cv2.IMREAD_UNCHANGED)
        cv2.imwrite(str(root / "train" / png.name), cv2.resize(im, (size, size), cv2.INTER_CUBIC))
    return root


def hits_fraction(ds, aabb: np.ndarray) -> float:
    """Fraction of opaque (alpha >= 128) test-view pixel rays that pass through ``aabb``."""
    k = ds.intrinsics
    hit = total = 0
    for i in ds.indices("test"):
        v, u = np.nonzero(ds.alpha[i] >= 128)
        d = np.stack([(u + 0.5 - k.cx) / k.fx, (v + 0.5 - k.cy) / k.fy, np.ones(len(u))], -1)
        d = d @ ds.poses[i, :3, :3].T
        o = ds.poses[i, :3, 3]
        with np.errstate(divide="ignore"):
            t0, t1 = (aabb[0] - o) / d, (aabb[1] - o) / d
        tmin, tmax = np.minimum(t0, t1).max(-1), np.maximum(t0, t1).min(-1)
        hit += int(((tmax >= tmin) & (tmax > 0)).sum())
        total += len(u)
    return hit / total


def plot_sectors(ds, summary: dict) -> None:
    """Top view of the train cameras around the scene centre, coloured by sector shard."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    up, centre = np.array(summary["up"]), np.array(summary["scene_centre"])
    fig, ax = plt.subplots(figsize=(5, 5))
    for s in summary["shards"]:
        idx = np.array(s["parent_index"])
        az = azimuths(ds.poses[idx, :3, 3], centre, up)
        r = np.linalg.norm(np.cross(ds.poses[idx, :3, 3] - centre, up), axis=1)
        ax.scatter(r * np.cos(az), r * np.sin(az), s=18, label=f"client {s['client']}")
    test = ds.indices("test")
    az = azimuths(ds.poses[test, :3, 3], centre, up)
    r = np.linalg.norm(np.cross(ds.poses[test, :3, 3] - centre, up), axis=1)
    ax.scatter(r * np.cos(az), r * np.sin(az), s=6, c="lightgray", label="test (all clients)")
    ax.scatter([0], [0], marker="+", c="k")
    ax.set_aspect("equal")
    ax.set_title("lego, 4 sector shards: camera centres seen from above")
    ax.legend(fontsize=7, loc="upper right")
    fig.tight_layout()
    fig.savefig(OUT.with_name("datasets_sectors.png"), dpi=110)
    plt.close(fig)


def main() -> int:
    if not (LEGO / "transforms_train.json").exists():
        print(f"lego not found at {LEGO}", file=sys.stderr)
        return 1
    rows: list[str] = []
    with tempfile.TemporaryDirectory() as tmp_dir:
        tmp = Path(tmp_dir)
        h5 = tmp / "lego.h5"
        for color in ("rgb", "gray"):
            t = median_seconds(
                lambda c=color: import_blender(LEGO, h5, 160, c, progress=False), REPEAT
            )
            mb = h5.stat().st_size / 1e6
            rows.append(
                f"| import lego 160 px {color} (400 views) | {t:.2f} s | file {mb:.1f} MB |"
            )
        big = upsampled_scene(tmp / "lego800", 800)
        t = median_seconds(lambda: import_blender(big, tmp / "b.h5", 160, progress=False), 1)
        rows.append(
            f"| import 100 views 800 px -> 160 px | {t:.2f} s | {1e3 * t / 100:.1f} ms/view |"
        )

        import_blender(LEGO, h5, 160, "rgb", progress=False)
        ds = open_dataset(h5)
        train = ds.indices("train")
        cube = lookat_cube(ds.poses, ds.intrinsics)
        vol_cube = float(np.prod(cube[1] - cube[0]))
        rows.append(
            f"| look-at cube fallback | - | volume {vol_cube:.2f}, test rays hit "
            f"{100 * hits_fraction(ds, cube):.2f} % |"
        )
        for grid in (32, 48, 64, 96):
            box = [None]

            def carve(g=grid, out=box):
                out[0] = carve_aabb(ds.alpha[train], ds.poses[train], ds.intrinsics, grid=g)

            t = median_seconds(carve, REPEAT)
            vol = float(np.prod(box[0][1] - box[0][0]))
            rows.append(
                f"| carve AABB, grid {grid} | {t:.2f} s | volume {vol:.2f} "
                f"({100 * vol / vol_cube:.0f} % of cube), test rays hit "
                f"{100 * hits_fraction(ds, box[0]):.2f} % |"
            )

        rng = np.random.default_rng(0)
        idx = rng.integers(0, ds.n, 2000)
        with h5py.File(h5) as f:
            images = f["images"]
            t = median_seconds(lambda: [images[int(i)] for i in idx], REPEAT)
        rows.append(f"| random read of one frame (lzf chunk) | {1e3 * t / len(idx):.3f} ms | |")
        for scheme in ("iid", "sector"):
            t = median_seconds(lambda s=scheme: shard_dataset(h5, tmp / s, 4, s), REPEAT)
            summary = json.loads((tmp / scheme / "summary.json").read_text())
            spans = [s.get("span_deg") for s in summary["shards"]]
            extra = f"sector spans {spans} deg" if scheme == "sector" else "4 x 25 train + 200 test"
            rows.append(f"| shard lego 4 clients {scheme} | {t:.2f} s | {extra} |")
        plot_sectors(ds, json.loads((tmp / "sector" / "summary.json").read_text()))
        t = median_seconds(lambda: export_transforms(h5, tmp / "export"), REPEAT)
        rows.append(f"| export-transforms lego (400 PNGs) | {t:.2f} s | |")

    table = "\n".join(["| step | time | notes |", "|---|---|---|", *rows])
    text = (
        "# datasets benchmark\n\n"
        "`nice .venv/bin/python benchmarks/datasets.py` (median of 3 unless 1 run; 2 shared "
        "cores).\n\n" + table + "\n"
    )
    print(text)
    OUT.parent.mkdir(parents=True, exist_ok=True)
    OUT.write_text(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
