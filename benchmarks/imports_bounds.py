"""Imports that bound what is seen: transforms.json captures without points, old vs new import.

Two real scenes, written as public tools write them, none with a point cloud:

- **object**: lego (the 160 px NeRF Synthetic renders) seen from one side only (cameras whose
  azimuth lies within 60 degrees of +x: a hand-held capture walks round part of an object),
  composited on white (no alpha), warped through an OpenCV lens, and posed as instant-ngp's
  ``colmap2nerf.py`` writes a capture: up along +z, the cameras' common look-at point at the
  origin, the camera centres scaled to a mean distance of 4 from it, ``aabb_scale`` 4, no
  ``aabb``, one ``transforms.json`` (every 8th frame is a test frame). The camera centres' box
  lies to one side of the origin and does not hold the object.
- **forward**: a real Himax HM01B0 sequence (``--himax``, default test_23) posed by
  ``dronecap ingest`` + ``sfm`` + ``split``, exported with ``export-transforms`` and its points
  dropped (no ``ply_file_path``, no ``aabb``).

Each is imported by the code before this change (``--old-tree``, default /work/main, run as a
subprocess with that tree first on PYTHONPATH) and by this tree, then trained with the default
``dronecap train`` for ``--steps`` (1 thread); the table gives where the bounds came from, the
box, whether it holds the look-at point and every view centre, and the test PSNR / SSIM. A
figure shows each scene's cameras and the two boxes from above.

Usage: ``nice .venv/bin/python benchmarks/imports_bounds.py --work /tmp/ib`` (the Himax
workspace, ``--himax-work``, must hold ``dataset.h5`` from ``ingest``/``sfm``/``split``).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
from _runs import lens_maps

REPO = Path(__file__).resolve().parents[1]
RESULTS = REPO / "benchmarks" / "results"
LEGO = REPO.parent / "shared" / "data" / "nerf_synthetic_160" / "lego"
LENS = (-0.12, 0.03, 0.001, -0.001)  # k1 k2 p1 p2: a mild barrel lens, OpenCV model
EARLIER = "\n## Notes"  # what follows it in the results file is kept when re-run
AZIMUTH_HALF = 60.0  # degrees: the object is seen from one side (a third of the way round)


def _rotation_to_z(up: np.ndarray) -> np.ndarray:
    """Rotation [3, 3] taking the unit vector ``up`` to +z (Rodrigues)."""
    z = np.array([0.0, 0.0, 1.0])
    v, c = np.cross(up, z), float(up @ z)
    if np.linalg.norm(v) < 1e-12:
        return np.eye(3) if c > 0 else np.diag([1.0, -1.0, -1.0])
    vx = np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])
    return np.eye(3) + vx + vx @ vx / (1 + c)


def object_capture(out: Path) -> Path:
    """Write the one-sided lego capture (see the module docstring) to ``out``; its folder."""
    import cv2

    from dronecap.datasets.blender import import_blender, opencv_to_opengl
    from dronecap.datasets.bounds import lookat_point
    from dronecap.datasets.format import open_dataset

    ds = open_dataset(import_blender(LEGO, out.parent / "lego_src.h5", progress=False))
    centres = ds.poses[:, :3, 3]
    az = np.degrees(np.arctan2(centres[:, 1], centres[:, 0]))
    keep = np.flatnonzero(np.abs(az) <= AZIMUTH_HALF)
    poses = ds.poses[keep].copy()
    # colmap2nerf: up (mean camera up, OpenGL +y = OpenCV -y) to +z, look-at to the origin,
    # mean camera distance 4; here a tilted, offset source frame first so the steps matter
    rng = np.random.default_rng(0)
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    rot0 = q * np.sign(np.linalg.det(q))
    shift = rng.normal(size=3) * 3
    poses[:, :3, :3] = rot0 @ poses[:, :3, :3]  # a COLMAP frame: rotated, scaled 2.7, shifted
    poses[:, :3, 3] = 2.7 * poses[:, :3, 3] @ rot0.T + shift
    up = -poses[:, :3, 1].mean(0)
    rot = _rotation_to_z(up / np.linalg.norm(up))
    poses[:, :3, :] = rot @ poses[:, :3, :]
    poses[:, :3, 3] -= lookat_point(poses)
    poses[:, :3, 3] *= 4.0 / np.linalg.norm(poses[:, :3, 3], axis=1).mean()
    pin = ds.intrinsics
    map_x, map_y = lens_maps(pin, LENS)
    (out / "images").mkdir(parents=True, exist_ok=True)
    frames = []
    for j, i in enumerate(keep):
        a = ds.alpha[i][:, :, None] / 255.0
        rgb = (ds.images[i] * a + 255.0 * (1 - a)).round().astype(np.uint8)[:, :, ::-1]
        warped = cv2.remap(rgb, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        name = f"images/{j:04d}.jpg"
        cv2.imwrite(str(out / name), warped, [cv2.IMWRITE_JPEG_QUALITY, 95])
        frames.append({"file_path": name, "transform_matrix": opencv_to_opengl(poses[j]).tolist()})
    meta = {"camera_model": "OPENCV", "fl_x": pin.fx, "fl_y": pin.fy, "cx": pin.cx, "cy": pin.cy,
            "w": pin.width, "h": pin.height, "aabb_scale": 4,
            **dict(zip(("k1", "k2", "p1", "p2"), LENS, strict=True)), "frames": frames}  # fmt: skip
    (out / "transforms.json").write_text(json.dumps(meta, indent=1))
    return out


def forward_capture(himax_dataset: Path, out: Path) -> Path:
    """Export the posed Himax dataset with ``export-transforms`` and drop its points and box."""
    _cli(REPO, "export-transforms", str(himax_dataset), "-o", str(out))
    for name in ("transforms.json", "transforms_train.json", "transforms_val.json",
                 "transforms_test.json"):  # fmt: skip
        path = out / name
        if path.exists():
            meta = json.loads(path.read_text())
            for key in ("ply_file_path", "aabb", "aabb_scale", "applied_transform"):
                meta.pop(key, None)
            path.write_text(json.dumps(meta, indent=1))
    (out / "sparse_pc.ply").unlink(missing_ok=True)
    return out


def _cli(tree: Path, *args: str) -> str:
    """Run ``dronecap ARGS`` with ``tree`` first on PYTHONPATH (1 thread); its stdout."""
    env = {**os.environ, "PYTHONPATH": str(tree), "OMP_NUM_THREADS": "1"}
    r = subprocess.run([sys.executable, "-m", "dronecap.cli", *args], env=env, cwd=tree,
                       capture_output=True, text=True)  # fmt: skip
    if r.returncode:
        raise SystemExit(f"dronecap {' '.join(args)} failed:\n{r.stderr[-2000:]}")
    return r.stdout


def check_bounds(dataset: Path) -> dict:
    """Where the bounds came from, the box, and whether it holds the look-at point and every
    camera's view centre (the point of its optical axis closest to the look-at point)."""
    from dronecap.datasets.bounds import lookat_point, view_centres
    from dronecap.datasets.format import open_dataset

    ds = open_dataset(dataset)
    c = lookat_point(ds.poses)
    lo, hi = ds.aabb
    vc = view_centres(ds.poses, c)
    inside = ((vc >= lo) & (vc <= hi)).all(1)
    return {
        "bounds_from": ds.attrs.get("bounds_from", "?"),
        "aabb": ds.aabb.round(3).tolist(),
        "lookat_inside": bool(((c >= lo) & (c <= hi)).all()),
        "view_centres_inside": f"{int(inside.sum())}/{len(inside)}",
        "poses": ds.poses,
    }


def background_of(dataset: Path) -> str:
    """The dataset's declared background colour and where it came from ("none" without)."""
    from dronecap.datasets.format import open_dataset

    ds = open_dataset(dataset)
    return "none" if ds.background is None else f"{list(ds.background)}"


def train(tree: Path, dataset: Path, run: Path, steps: int) -> dict:
    """Default ``dronecap train`` of ``tree`` for ``steps`` on 1 thread: test PSNR / SSIM. A
    finished run of the same dataset and steps in ``run`` is reused (runs can be started side
    by side with the same command, then tabulated here)."""
    done = run / "metrics.json"
    if done.exists():
        cfg = json.loads((run / "run.json").read_text())
        if Path(cfg["dataset"]) == dataset and cfg["config"]["steps"] == steps:
            test = json.loads(done.read_text())["test"]
            return {"psnr": test["psnr"], "ssim": test["ssim"]}
    _cli(tree, "train", str(dataset), "--steps", str(steps), "--out", str(run), "--threads", "1",
         "--no-progress")  # fmt: skip
    test = json.loads((run / "metrics.json").read_text())["test"]
    return {"psnr": test["psnr"], "ssim": test["ssim"]}


def figure(rows: list[dict], path: Path) -> None:
    """Top views (x, y) of each scene: camera centres, look-at point, old and new boxes."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from dronecap.datasets.bounds import lookat_point

    scenes = sorted({r["scene"] for r in rows})
    fig, axes = plt.subplots(1, len(scenes), figsize=(5 * len(scenes), 5), squeeze=False)
    for ax, scene in zip(axes[0], scenes, strict=True):
        for r, colour in zip([r for r in rows if r["scene"] == scene], ("tab:red", "tab:green"),
                             strict=False):  # fmt: skip
            p = r["poses"]
            lo, hi = np.asarray(r["aabb"])
            ax.plot(*p[:, :2, 3].T, ".", color=colour, ms=3, label=f"{r['code']} cameras")
            ax.add_patch(plt.Rectangle(lo[:2], *(hi - lo)[:2], fill=False, color=colour,
                                       label=f"{r['code']}: {r['psnr']:.1f} dB"))  # fmt: skip
            c = lookat_point(p)
            ax.plot(*c[:2], "x", color=colour, ms=10)
        ax.set_title(f"{scene} (x: look-at point)")
        ax.set_aspect("equal")
        ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--work", type=Path, required=True)
    p.add_argument("--himax-work", type=Path, help="workspace with dataset.h5 (forward scene)")
    p.add_argument("--scenes", nargs="+", default=["object", "forward"], help="scenes to run")
    p.add_argument("--codes", nargs="+", default=["old", "new"], help="old and/or new code")
    p.add_argument("--old-tree", type=Path, default=Path("/work/main"))
    p.add_argument("--steps", type=int, default=1500)
    args = p.parse_args()
    load = os.getloadavg()
    args.work.mkdir(parents=True, exist_ok=True)
    makers = {
        "object": lambda: object_capture(args.work / "object"),
        "forward": lambda: forward_capture(args.himax_work / "dataset.h5", args.work / "forward"),
    }
    scenes = {name: makers[name]() for name in args.scenes}
    rows = []
    for scene, src in scenes.items():
        for code, tree in [
            c for c in (("old", args.old_tree), ("new", REPO)) if c[0] in args.codes
        ]:
            ds = args.work / f"{scene}_{code}.h5"
            out = _cli(tree, "import-transforms", str(src), "-o", str(ds))
            row = {"scene": scene, "code": code, **check_bounds(ds)}
            row.update(train(tree, ds, args.work / f"run_{scene}_{code}", args.steps))
            row["import_says"] = out.strip().splitlines()[-1]
            row["background"] = background_of(ds)
            rows.append(row)
            print(scene, code, row["bounds_from"], f"{row['psnr']:.2f} dB", flush=True)
    end = os.getloadavg()
    RESULTS.mkdir(exist_ok=True)
    figure(rows, RESULTS / "imports_bounds.png")
    lines = [
        "| scene | code | bounds from | AABB | look-at inside | view centres inside | "
        "background | test PSNR dB | SSIM |",
        "|---|---|---|---|---|---|---|---:|---:|",
    ]
    for r in rows:
        lines.append(
            f"| {r['scene']} | {r['code']} | {r['bounds_from']} | {r['aabb']} | "
            f"{r['lookat_inside']} | {r['view_centres_inside']} | {r['background']} | "
            f"{r['psnr']:.2f} | "
            f"{r['ssim']:.3f} |"
        )
    text = (
        "# Imports that bound what is seen (transforms.json without points)\n\n"
        f"Command: `nice .venv/bin/python benchmarks/imports_bounds.py --work {args.work} "
        f"--himax-work {args.himax_work} --steps {args.steps} --scenes {' '.join(args.scenes)} "
        f"--codes {' '.join(args.codes)}`; "
        f"old = {args.old_tree}; default `dronecap train --steps {args.steps} --threads 1`; load "
        f"average at start {load[0]:.1f} / {load[1]:.1f} / {load[2]:.1f}, at the end "
        f"{end[0]:.1f} / {end[1]:.1f} / {end[2]:.1f}.\n\n" + "\n".join(lines) + "\n\n"
        "Figure: `imports_bounds.png` (top view: cameras, look-at point, boxes).\n"
    )
    print(text)
    out = RESULTS / "imports_bounds.md"
    old = out.read_text() if out.exists() else ""
    kept = old[old.index(EARLIER) :] if EARLIER in old else ""  # notes and earlier tables
    out.write_text(text + kept)


if __name__ == "__main__":
    main()
