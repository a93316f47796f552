"""Import a NeRF Synthetic 360° scene (Blender layout) into a dronecap dataset.

The layout: ``transforms_{train,val,test}.json`` beside folders of RGBA PNGs. Each JSON holds
``camera_angle_x`` (horizontal field of view, radians) and ``frames`` with a ``file_path``
(relative, usually without ``.png``) and a ``transform_matrix`` (camera-to-world, OpenGL
camera axes: x right, y up, z backwards).

What the importer stores:

- images: the straight (not premultiplied) colour of the PNG, resized with area interpolation
  (premultiplied by alpha while resizing so transparent pixels do not bleed into the edges),
  as RGB or as gray with BT.601 luma weights (0.299 R + 0.587 G + 0.114 B, as OpenCV);
- alpha: uint8 [N, H, W]; background white (1.0 per channel): the trainer composites
  ``c·a + background·(1 − a)``;
- poses converted to OpenCV axes; fx = fy = W / (2 tan(camera_angle_x / 2)), cx = W/2, cy = H/2;
- the official split (train 0, val 1, test 2); names ``train/r_0`` etc.; source_index = the
  frame's position in its JSON;
- the AABB carved from the train views' alpha masks (:func:`bounds.carve_aabb`), or the
  cameras' common look-at cube if carving fails; per-view near/far from that AABB.
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import numpy as np

from dronecap.datasets.bounds import carve_aabb, lookat_cube, near_far_from_aabb
from dronecap.datasets.format import SPLITS, Dataset, Intrinsics, provenance, write_dataset
from dronecap.datasets.import_scene import read_images
from dronecap.datasets.safe_paths import inside_folder
from dronecap.errors import InputError
from dronecap.limits import read_image

LUMA_BT601 = (0.299, 0.587, 0.114)
BACKGROUND = 1.0  # white, per channel
_GL_TO_CV = np.diag([1.0, -1.0, -1.0, 1.0])


def opengl_to_opencv(c2w: np.ndarray) -> np.ndarray:
    """Camera-to-world poses with OpenGL camera axes -> OpenCV camera axes (and back).

    Flips the camera's y and z axes (right-multiplies by diag(1, -1, -1, 1)); the world frame is
    unchanged. The operation is its own inverse, so it also converts OpenCV -> OpenGL.

    Args:
        c2w: float [N, 4, 4] (or [4, 4]) camera-to-world.

    Returns:
        float64 array of the same shape.
    """
    return np.asarray(c2w, dtype=np.float64) @ _GL_TO_CV


opencv_to_opengl = opengl_to_opencv


def import_blender(
    scene_dir: str | Path,
    out_path: str | Path,
    resolution: int = 160,
    color: str = "rgb",
    progress: bool = True,
) -> Path:
    """Read a Blender-layout scene and write it as a dronecap dataset (kind "dataset").

    Args:
        scene_dir: folder holding ``transforms_train.json`` (val/test JSONs optional) and PNGs.
        out_path: the ``.h5`` to write (atomically).
        resolution: stored image width in pixels (height keeps the source aspect ratio).
        color: "rgb" (C = 3) or "gray" (C = 1, BT.601 luma).
        progress: show progress while reading images.

    Returns:
        ``out_path`` as a Path.

    Raises:
        InputError: missing/invalid JSON or images, unknown colour, bad resolution.
    """
    scene_dir = Path(scene_dir)
    if color not in ("rgb", "gray"):
        raise InputError(f"unknown colour {color!r}: use 'rgb' or 'gray'")
    if resolution < 1:
        raise InputError(f"resolution must be a positive number of pixels, got {resolution}")
    if not scene_dir.is_dir():
        raise InputError(
            "not a folder (expected a Blender scene with transforms_*.json)", scene_dir
        )
    frames, angle_x, hashes = _read_transforms(scene_dir)
    files = [_image_path(scene_dir, fr) for _, _, fr in frames]
    read = read_images(files, resolution, color, progress)
    im = read.images
    al = read.alpha if read.alpha is not None else np.full(im.shape[:3], 255, np.uint8)
    h, w = im.shape[1:3]
    f = w / (2 * np.tan(angle_x / 2))
    intr = Intrinsics(fx=f, fy=f, cx=w / 2, cy=h / 2, width=w, height=h)
    poses = opengl_to_opencv(np.array([fr["transform_matrix"] for _, _, fr in frames], float))
    split = np.array([SPLITS[s] for s, _, _ in frames], np.int8)
    train = split == SPLITS["train"]
    aabb = carve_aabb(al[train], poses[train], intr)
    bounds_from = "alpha carving"
    if aabb is None:
        aabb, bounds_from = lookat_cube(poses, intr), "look-at cube (carving failed)"
    hashes["images"] = _hash_files(files, scene_dir)
    ds = Dataset(
        images=im,
        kind="dataset",
        alpha=al,
        poses=poses,
        intrinsics=intr,
        names=[f"{s}/{Path(fr['file_path']).name}" for s, _, fr in frames],
        source_index=np.array([i for _, i, _ in frames], np.int64),
        split=split,
        near_far=near_far_from_aabb(poses, aabb),
        aabb=aabb,
        normalization=np.eye(4),
        background=(BACKGROUND,) * im.shape[3],
        provenance=provenance(
            "import-blender",
            {"scene_dir": str(scene_dir), "resolution": resolution, "color": color},
            hashes,
        ),
        attrs={
            "source": "blender",
            "scene": scene_dir.name,
            "camera_angle_x": angle_x,
            "source_size": list(read.source_size),
            "bounds_from": bounds_from,
            "luma_weights": list(LUMA_BT601) if color == "gray" else None,
        },
    )
    return write_dataset(out_path, ds)


def _read_transforms(scene_dir: Path) -> tuple[list[tuple[str, int, dict]], float, dict[str, str]]:
    """(split, index in its JSON, frame) for every frame; camera_angle_x; the JSONs' hashes."""
    frames: list[tuple[str, int, dict]] = []
    angles: dict[str, float] = {}
    hashes: dict[str, str] = {}
    for split in SPLITS:
        path = scene_dir / f"transforms_{split}.json"
        if not path.exists():
            if split == "train":
                raise InputError("no such file (not a Blender scene folder?)", path)
            continue
        raw = path.read_bytes()
        hashes[path.name] = hashlib.sha256(raw).hexdigest()
        try:
            meta = json.loads(raw)
            angles[split] = float(meta["camera_angle_x"])
            entries = list(meta["frames"])
            for i, fr in enumerate(entries):
                m = np.asarray(fr["transform_matrix"], float)
                if m.shape != (4, 4) or not np.isfinite(m).all():
                    raise ValueError(f"frame {i}: transform_matrix is not a finite 4x4 matrix")
                str(fr["file_path"])
        except (ValueError, KeyError, TypeError) as err:
            raise InputError(f"invalid transforms file: {err}", path) from None
        if not entries:
            raise InputError("has no frames", path)
        frames += [(split, i, fr) for i, fr in enumerate(entries)]
    angle = angles["train"]
    for split, a in angles.items():
        if not np.isclose(a, angle, rtol=1e-6):
            raise InputError(
                f"camera_angle_x {a} differs from the train split's {angle}",
                scene_dir / f"transforms_{split}.json",
            )
    if not 0 < angle < np.pi:
        raise InputError(f"camera_angle_x {angle} is not in (0, pi)", scene_dir)
    return frames, angle, hashes


def _image_path(scene_dir: Path, frame: dict) -> Path:
    p = scene_dir / str(frame["file_path"])
    return inside_folder(scene_dir, p if p.suffix else p.with_name(p.name + ".png"))


def _read_rgba(path: Path) -> np.ndarray:
    """uint8 [H, W, 4] RGBA of a PNG (alpha 255 when the file has none)."""
    import cv2

    im = read_image(path)  # its header's size checked first: no decompression bomb
    if im is None:
        raise InputError("missing or unreadable image", path)
    if im.dtype == np.uint16:
        im = (im.astype(np.float64) / 257).round().astype(np.uint8)
    if im.dtype != np.uint8:
        raise InputError(f"unsupported pixel type {im.dtype}", path)
    if im.ndim == 2:
        im = im[:, :, None]
    conv = {1: cv2.COLOR_GRAY2RGBA, 3: cv2.COLOR_BGR2RGBA, 4: cv2.COLOR_BGRA2RGBA}
    if im.shape[2] not in conv:
        raise InputError(f"unsupported channel count {im.shape[2]}", path)
    return cv2.cvtColor(im, conv[im.shape[2]])


def _resize(rgba: np.ndarray, width: int) -> tuple[np.ndarray, np.ndarray]:
    """Area-resize RGBA [H, W, 4] to ``width``: straight colour float32 [h, w, 3], alpha uint8."""
    import cv2

    h0, w0 = rgba.shape[:2]
    height = max(1, round(h0 * width / w0))
    if (height, width) == (h0, w0):
        return rgba[:, :, :3].astype(np.float32), rgba[:, :, 3].copy()
    a = rgba[:, :, 3].astype(np.float32) / 255
    prem = rgba[:, :, :3].astype(np.float32) * a[:, :, None]
    prem = cv2.resize(prem, (width, height), interpolation=cv2.INTER_AREA)
    a = cv2.resize(a, (width, height), interpolation=cv2.INTER_AREA)
    rgb = np.where(a[:, :, None] > 1e-6, prem / np.maximum(a, 1e-6)[:, :, None], 0.0)
    return rgb.astype(np.float32), np.clip(a * 255 + 0.5, 0, 255).astype(np.uint8)


def _to_color(rgb: np.ndarray, color: str) -> np.ndarray:
    """float [H, W, 3] in 0..255 -> uint8 [H, W, 3] (rgb) or [H, W, 1] (gray, BT.601)."""
    out = rgb @ np.asarray(LUMA_BT601, np.float32)[:, None] if color == "gray" else rgb
    return np.clip(out + 0.5, 0, 255).astype(np.uint8)


def _hash_files(files: list[Path], root: Path) -> str:
    """SHA-256 over the relative names and bytes of ``files`` (sorted by name)."""
    h = hashlib.sha256()
    for p in sorted(files, key=lambda q: q.relative_to(root).as_posix()):
        h.update(p.relative_to(root).as_posix().encode())
        h.update(p.read_bytes())
    return h.hexdigest()
