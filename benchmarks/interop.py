"""Interop benchmark: exports that other tools load, imports that keep the lens.

Run: ``OMP_NUM_THREADS=1 nice .venv/bin/python benchmarks/interop.py [--steps 1500]``
(needs ../shared/data/nerf_synthetic_160). Prints a table and writes it to
``benchmarks/results/interop.md``.

1. **A captured flight** (simulate 240 frames -> ingest -> sfm -> split -> export-transforms):
   how far the SfM model's observations land from the projection of their points through the
   exported ``transforms.json`` (its camera, its OpenGL poses) — the export's geometry against
   COLMAP's own residuals; then ``import-transforms`` of the export against the dataset.
2. **A distorted dataset**: lego's 160 px views warped through a known OPENCV lens and written as
   a nerfstudio dataset (``k1 k2 p1 p2``); imported, then trained twice for the same steps on
   one thread: with the imported lens, and with the lens dropped (what a loader that ignores the
   distortion keys would train on). Test PSNR on the same held-out views.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np
from _runs import lens_maps

from dronecap.camera import Camera
from dronecap.cli import main as dronecap
from dronecap.datasets.blender import import_blender, opencv_to_opengl
from dronecap.datasets.export import export_transforms
from dronecap.datasets.format import open_dataset, write_dataset
from dronecap.datasets.import_transforms import import_transforms

REPO = Path(__file__).resolve().parents[1]
LEGO = REPO.parent / "shared" / "data" / "nerf_synthetic_160" / "lego"
OUT = REPO / "benchmarks" / "results" / "interop.md"
LENS = (-0.28, 0.09, 0.004, -0.003)  # k1 k2 p1 p2 of the synthetic lens (barrel)
sys.path.insert(0, str(REPO))  # the test suite's loader rules (tests/datasets/interop.py)
from tests.datasets.interop import reprojection_px  # noqa: E402


def flight_export(work: Path) -> dict:
    """Part 1 figures."""
    import pycolmap

    w = ["--workdir", str(work)]
    t0 = time.perf_counter()
    steps = [
        ["simulate", "--frames", "240", "--seed", "1"],
        ["ingest", str(work / "flight.mp4")],
        ["sfm", "--gt", str(work / "flight.json")],
        ["split"],
    ]
    for cmd in steps:
        assert dronecap(["-q", *cmd, *w]) == 0, cmd
    t_pipeline = time.perf_counter() - t0
    t = time.perf_counter()
    res = export_transforms(work / "dataset.h5", work / "export", work / "sfm" / "model")
    t_export = time.perf_counter() - t
    meta = json.loads((work / "export" / "transforms.json").read_text())
    k = Camera(meta["fl_x"], meta["fl_y"], meta["cx"], meta["cy"], meta["w"], meta["h"],
               *(("OPENCV", tuple(meta[n] for n in ("k1", "k2", "p1", "p2")))
                 if meta["camera_model"] == "OPENCV" else ()))  # fmt: skip
    rec = pycolmap.Reconstruction(str(work / "export" / "colmap" / "sparse" / "0"))
    errs = reprojection_px(rec, meta, k)
    t = time.perf_counter()
    back = open_dataset(import_transforms(work / "export", work / "back.h5", progress=False))
    t_import = time.perf_counter() - t
    ds = open_dataset(work / "dataset.h5")
    return {
        "frames": res.frames,
        "splits": res.split_counts,
        "points": res.points,
        "observations": res.observations,
        "camera": meta["camera_model"],
        "reproj_median_px": float(np.median(errs)),
        "reproj_p90_px": float(np.percentile(errs, 90)),
        "roundtrip_pose_max": float(np.abs(back.poses - ds.poses).max()),
        "roundtrip_images_equal": bool(np.array_equal(back.images, ds.images)),
        "pipeline_s": t_pipeline,
        "export_s": t_export,
        "import_s": t_import,
    }


def distorted_lego(work: Path, n_test: int) -> Path:
    """lego at 160 px seen through LENS (RGBA PNGs + nerfstudio transforms.json); test views are
    the first ``n_test`` of lego's test split."""
    ds = open_dataset(import_blender(LEGO, work / "lego.h5", progress=False))
    pin = ds.intrinsics
    map_x, map_y = lens_maps(pin, LENS)
    keep = np.concatenate([ds.indices("train"), ds.indices("test")[:n_test]])
    (work / "ns" / "images").mkdir(parents=True)
    frames = []
    for i in keep:
        rgba = np.dstack([ds.images[i][:, :, ::-1], ds.alpha[i]])
        warped = cv2.remap(rgba, map_x, map_y, cv2.INTER_LINEAR, borderValue=(0, 0, 0, 0))
        name = f"images/{i:03d}.png"
        cv2.imwrite(str(work / "ns" / name), warped)
        frames.append(
            {"file_path": name, "transform_matrix": opencv_to_opengl(ds.poses[i]).tolist()}
        )
    split = {"train": [f["file_path"] for f in frames[: len(ds.indices("train"))]]}
    split["val"] = split["test"] = [f["file_path"] for f in frames[len(split["train"]) :]]
    lens_keys = dict(zip(("k1", "k2", "p1", "p2"), LENS, strict=True))
    meta = {"camera_model": "OPENCV", "fl_x": pin.fx, "fl_y": pin.fy, "cx": pin.cx, "cy": pin.cy,
            "w": pin.width, "h": pin.height, **lens_keys, "frames": frames,
            **{f"{s}_filenames": v for s, v in split.items()}}  # fmt: skip
    (work / "ns" / "transforms.json").write_text(json.dumps(meta))
    return work / "ns"


def train_psnr(dataset: Path, run: Path, steps: int) -> tuple[float, float]:
    """(test PSNR, wall seconds) of `dronecap train --preset tiny-dronerf` for ``steps``."""
    t = time.perf_counter()
    cmd = [sys.executable, "-m", "dronecap.cli", "train", str(dataset), "--preset",
           "tiny-dronerf", "--steps", str(steps), "--out", str(run), "--threads", "1",
           "--no-progress"]  # fmt: skip
    subprocess.run(cmd, check=True, env={**os.environ, "OMP_NUM_THREADS": "1"})
    return json.loads((run / "metrics.json").read_text())["test"]["psnr"], time.perf_counter() - t


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--steps", type=int, default=1500, help="training steps per lens variant")
    p.add_argument("--test-views", type=int, default=25, help="lego test views scored")
    args = p.parse_args()
    load = os.getloadavg()
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        flight = flight_export(tmp / "flight")
        scene = distorted_lego(tmp / "lego", args.test_views)
        ds = open_dataset(import_transforms(scene, tmp / "with_lens.h5", progress=False))
        dropped = dataclasses.replace(ds, intrinsics=ds.intrinsics.pinhole())
        write_dataset(tmp / "no_lens.h5", dropped)
        with_lens = train_psnr(tmp / "with_lens.h5", tmp / "run_lens", args.steps)
        no_lens = train_psnr(tmp / "no_lens.h5", tmp / "run_nolens", args.steps)
    f, sp = flight, flight["splits"]
    lens_row = f"distorted lego, {args.steps} steps, lens {LENS}: test PSNR with the imported lens"
    rows = [
        ("flight: frames / train / val / test",
         f"{f['frames']} / {sp['train']} / {sp['val']} / {sp['test']} (val = the test split)"),
        ("flight: sparse points / observations exported", f"{f['points']} / {f['observations']}"),
        ("flight: camera model", f["camera"]),
        ("flight: COLMAP observations vs projection through transforms.json",
         f"median {f['reproj_median_px']:.3f} px, p90 {f['reproj_p90_px']:.3f} px"),
        ("flight: import-transforms of the export",
         f"poses max diff {f['roundtrip_pose_max']:.1e}, "
         f"images equal: {f['roundtrip_images_equal']}"),
        ("flight: export / import time", f"{f['export_s']:.1f} s / {f['import_s']:.1f} s"),
        (lens_row, f"{with_lens[0]:.2f} dB ({with_lens[1]:.0f} s)"),
        ("... with the lens dropped (pinhole)", f"{no_lens[0]:.2f} dB ({no_lens[1]:.0f} s)"),
    ]  # fmt: skip
    table = "| what | measured |\n|---|---|\n" + "\n".join(f"| {a} | {b} |" for a, b in rows)
    text = (
        "# Interop: exports other tools load, imports that keep the lens\n\n"
        f"Command: `OMP_NUM_THREADS=1 nice .venv/bin/python benchmarks/interop.py --steps "
        f"{args.steps} --test-views {args.test_views}`; load average at start "
        f"{load[0]:.1f} / {load[1]:.1f} / {load[2]:.1f} (2 shared cores, single-thread training)."
        f"\n\n{table}\n"
    )
    print(text)
    OUT.write_text(text)


if __name__ == "__main__":
    main()
