"""A NeRF Synthetic split as a "flight" with exact ground truth, for SfM tests and benchmarks.

The 200 lego test views lie on a smooth orbit: read in order, they behave like a video. This
module composites them on white, converts them to gray (as ingest would store a drone's frames)
and returns a kind="frames" dataset plus the ground truth in the simulator's poses.json layout.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

from dronecap.datasets.blender import opengl_to_opencv
from dronecap.datasets.format import Dataset, Intrinsics
from dronecap.errors import InputError


def blender_flight(
    scene_dir: str | Path,
    split: str = "test",
    start: int = 0,
    count: int | None = None,
    step: int = 1,
) -> tuple[Dataset, dict[str, Any]]:
    """Frames ``start, start+step, ...`` (``count`` of them) of a Blender split.

    Returns:
        (frames dataset: gray uint8 [N, H, W, 1] with names, source_index = position in the
        split's JSON, timestamps at 30 fps, intrinsics; ground truth dict with "fps",
        "intrinsics" and "frames": [{"index", "timestamp", "c2w"}], c2w in OpenCV axes).
    """
    import cv2

    scene_dir = Path(scene_dir)
    meta_path = scene_dir / f"transforms_{split}.json"
    if not meta_path.exists():
        raise InputError("no such Blender split file", meta_path)
    meta = json.loads(meta_path.read_text())
    chosen = list(range(start, len(meta["frames"]), step))[:count]
    images, poses = [], []
    for i in chosen:
        fr = meta["frames"][i]
        path = scene_dir / (fr["file_path"].removeprefix("./") + ".png")
        rgba = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        if rgba is None or rgba.ndim != 3 or rgba.shape[2] != 4:
            raise InputError("not an RGBA PNG", path)
        a = rgba[..., 3:4].astype(np.float32) / 255.0
        bgr = rgba[..., :3].astype(np.float32) * a + 255.0 * (1.0 - a)
        gray = cv2.cvtColor(np.round(bgr).astype(np.uint8), cv2.COLOR_BGR2GRAY)
        images.append(gray[..., None])
        poses.append(fr["transform_matrix"])
    im = np.stack(images)
    h, w = im.shape[1:3]
    f = w / (2 * np.tan(meta["camera_angle_x"] / 2))
    k = Intrinsics(fx=f, fy=f, cx=w / 2, cy=h / 2, width=w, height=h)
    c2w = opengl_to_opencv(np.array(poses, dtype=np.float64))
    fps = 30.0
    index = np.array(chosen, dtype=np.int64)
    ds = Dataset(
        images=im,
        kind="frames",
        intrinsics=k,
        names=[f"{split}/r_{i}" for i in chosen],
        source_index=index,
        timestamps=index / fps,
    )
    gt = {
        "fps": fps,
        "intrinsics": {"fx": f, "fy": f, "cx": w / 2, "cy": h / 2, "width": w, "height": h},
        "frames": [
            {"index": int(i), "timestamp": float(i / fps), "c2w": m.tolist()}
            for i, m in zip(index, c2w, strict=True)
        ],
    }
    return ds, gt
