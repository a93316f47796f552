"""The rules other tools apply when they load our exports, written out from their loaders, and a
pycolmap model maker for import tests.

- :func:`nerfstudio_rules`: what nerfstudio 1.1.5's ``nerfstudio-data`` dataparser
  (``nerfstudio_dataparser.py``) and its image loader need from ``transforms.json`` for
  ``ns-train`` (train and val splits) and ``ns-eval`` (test);
- :func:`ngp_lens` / :func:`ngp_rules`: what instant-ngp's ``nerf_loader.cu`` reads (focal length
  lookup order, the four lens slots shared by k3/p1 and k4/p2, ``is_fisheye``, cx needs w);
- :func:`reprojection_px`: how far a COLMAP model's observations land from their points seen
  through an exported ``transforms.json``'s poses.
No nerfstudio or instant-ngp install is needed: the rules are plain key checks.
"""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np

# nerfstudio.cameras.cameras.CAMERA_MODEL_TO_TYPE (1.1.5)
NERFSTUDIO_MODELS = {
    "SIMPLE_PINHOLE", "PINHOLE", "SIMPLE_RADIAL", "RADIAL", "OPENCV", "OPENCV_FISHEYE",
    "EQUIRECTANGULAR", "OMNIDIRECTIONALSTEREO_L", "OMNIDIRECTIONALSTEREO_R", "VR180_L",
    "VR180_R", "ORTHOPHOTO", "FISHEYE624",
}  # fmt: skip
INTRINSIC_KEYS = ("fl_x", "fl_y", "cx", "cy", "h", "w")


def nerfstudio_rules(folder: Path) -> list[str]:
    """Violations of nerfstudio's dataparser rules by ``folder/transforms.json`` (empty: loads)."""
    bad: list[str] = []
    meta = json.loads((folder / "transforms.json").read_text())
    frames = meta.get("frames")
    if not isinstance(frames, list) or not frames:
        return ["no frames"]
    for key in INTRINSIC_KEYS:  # top level (fixed) or in every frame
        if key not in meta and not all(key in f for f in frames):
            bad.append(f"{key} neither top-level nor in every frame")
    for key in ("k1", "k2", "k3", "k4", "p1", "p2", *INTRINSIC_KEYS):
        if key in meta and not isinstance(meta[key], int | float):
            bad.append(f"{key} is not a number")
    if "camera_model" in meta and meta["camera_model"] not in NERFSTUDIO_MODELS:
        bad.append(f"camera_model {meta['camera_model']} unknown to nerfstudio")
    files = []
    for i, fr in enumerate(frames):
        m = np.asarray(fr.get("transform_matrix"), float)
        if m.shape != (4, 4) or not np.isfinite(m).all():
            bad.append(f"frame {i}: transform_matrix not a finite 4x4")
        path = (folder / fr["file_path"]).resolve()
        files.append(path)
        im = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        if im is None:
            bad.append(f"frame {i}: image {fr['file_path']} missing")
            continue
        if im.dtype != np.uint8 or (im.ndim == 3 and im.shape[2] not in (3, 4)):
            bad.append(f"frame {i}: image must be uint8 gray/RGB/RGBA")
        w, h = fr.get("w", meta.get("w")), fr.get("h", meta.get("h"))
        if (im.shape[1], im.shape[0]) != (w, h):
            bad.append(f"frame {i}: image is {im.shape[1]}x{im.shape[0]}, w/h say {w}x{h}")
    lists = {s: meta.get(f"{s}_filenames") for s in ("train", "val", "test")}
    if any(v is not None for v in lists.values()):  # one present: all must be (RuntimeError)
        known = set(files)
        for s, names in lists.items():
            if names is None:
                bad.append(f"{s}_filenames missing while another split list is present")
                continue
            missing = {n for n in names if (folder / n).resolve() not in known}
            if missing:
                bad.append(f"{s}_filenames names unknown files {sorted(missing)[:3]}")
        for s in ("train", "val"):  # ns-train builds both datasets; an empty one fails
            if lists[s] is not None and not lists[s]:
                bad.append(f"{s}_filenames is empty")
    if "applied_transform" in meta:
        a = np.asarray(meta["applied_transform"], float)
        if a.shape != (3, 4) or not np.isfinite(a).all():
            bad.append("applied_transform is not a finite 3x4")
    if "ply_file_path" in meta:
        import pytest

        o3d = pytest.importorskip(
            "open3d", reason="the [sim] extra: nerfstudio reads the PLY with it"
        )

        pcd = o3d.io.read_point_cloud(str(folder / meta["ply_file_path"]))
        if len(pcd.points) == 0:
            bad.append("ply_file_path: no points")
        if len(pcd.colors) != len(pcd.points):
            bad.append("ply_file_path: points without colours")
    return bad


def ngp_lens(keys: dict) -> tuple[str, np.ndarray]:
    """instant-ngp's read_lens: (mode, 4 params) from a JSON object's k1..k4, p1, p2."""
    params = np.zeros(4)
    mode = "Perspective"
    fisheye = bool(keys.get("is_fisheye", False))
    for name, slot in (("k1", 0), ("k2", 1), ("k3", 2), ("k4", 3), ("p1", 2), ("p2", 3)):
        if name in keys:
            params[slot] = float(keys[name])
            if params[slot] != 0:
                mode = "OpenCVFisheye" if fisheye else "OpenCV"
    return mode, params


def ngp_rules(path: Path, must_not_contain: set[str] = frozenset()) -> list[str]:
    """Violations of instant-ngp's loader rules by one transforms file (empty: loads)."""
    bad: list[str] = []
    meta = json.loads(path.read_text())
    frames = meta.get("frames")
    if not isinstance(frames, list) or not frames:
        return ["no frames"]
    for obj, where in [(meta, "top level")] + [(f, f"frame {i}") for i, f in enumerate(frames)]:
        if "cx" in obj and "w" not in obj:
            bad.append(f"{where}: cx without w")
        if "cy" in obj and "h" not in obj:
            bad.append(f"{where}: cy without h")
    if "aabb_scale" in meta:
        s = meta["aabb_scale"]
        if not (isinstance(s, int) and 1 <= s <= 128 and s & (s - 1) == 0):
            bad.append(f"aabb_scale {s} is not a power of two in 1..128")
    if "aabb" in meta and np.asarray(meta["aabb"], float).shape != (2, 3):
        bad.append("aabb is not [[min], [max]]")
    for i, fr in enumerate(frames):
        if not any(k in o for o in (meta, fr) for k in ("x_fov", "fl_x", "camera_angle_x")):
            bad.append(f"frame {i}: Couldn't read fov")
        m = np.asarray(fr.get("transform_matrix"), float)
        if m.shape[0] < 3 or m.shape[1] != 4:
            bad.append(f"frame {i}: transform_matrix not 3x4 or 4x4")
        p = path.parent / fr["file_path"]
        if not p.exists() and not any(p.with_suffix(s).exists() for s in (".png", ".jpg")):
            bad.append(f"frame {i}: Could not find image file {fr['file_path']}")
        if fr["file_path"] in must_not_contain:
            bad.append(f"frame {i}: {fr['file_path']} must not be in this file")
    return bad


def lego_colmap_model(ds, out: Path, n_views: int = 24, n_points: int = 400, seed: int = 0):
    """A COLMAP model of ``n_views`` train views of an imported lego dataset, made with pycolmap
    in a "COLMAP frame" that differs from the dataset's by a similarity, with exact keypoints of
    random points inside the AABB. Writes ``out/sparse`` (binary)
    and ``out/images`` (PNGs at the dataset size, the names the model uses).

    Returns:
        (the similarity S [4, 4] with x_colmap = S @ x_dataset, frame indices used).
    """
    import pycolmap
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(seed)
    s = np.eye(4)
    s[:3, :3] = 3.7 * Rotation.from_euler("xyz", [20, -35, 110], degrees=True).as_matrix()
    s[:3, 3] = [5.0, -2.0, 1.5]
    k = ds.intrinsics
    idx = np.flatnonzero(ds.split == 0)[:n_views]
    rec = pycolmap.Reconstruction()
    cam = pycolmap.Camera(
        model="PINHOLE", width=k.width, height=k.height, params=[k.fx, k.fy, k.cx, k.cy]
    )
    cam.camera_id = 1
    rec.add_camera_with_trivial_rig(cam)
    (out / "images").mkdir(parents=True)
    lo, hi = ds.aabb
    pts = lo + (hi - lo) * rng.uniform(0.2, 0.8, (n_points, 3))  # dataset frame
    tracks = [[] for _ in range(n_points)]
    for j, f in enumerate(idx):
        c2w_col = s @ ds.poses[f]  # similarity on the pose: rescale the rotation back
        c2w_col[:3, :3] /= 3.7
        w2c = np.linalg.inv(c2w_col)
        pc = (pts - ds.poses[f, :3, 3]) @ ds.poses[f, :3, :3]
        uv = np.stack([k.fx * pc[:, 0] / pc[:, 2] + k.cx, k.fy * pc[:, 1] / pc[:, 2] + k.cy], 1)
        ok = np.flatnonzero((pc[:, 2] > 0) & (uv >= 0).all(1) & (uv < [k.width, k.height]).all(1))
        for n, p in enumerate(ok):
            tracks[p].append((j + 1, n))
        name = f"r_{f:03d}.png"
        image = pycolmap.Image(name=name, keypoints=uv[ok], camera_id=1, image_id=j + 1)
        rec.add_image_with_trivial_frame(
            image, pycolmap.Rigid3d(pycolmap.Rotation3d(w2c[:3, :3]), w2c[:3, 3])
        )
        bgr = ds.images[f][:, :, ::-1]
        cv2.imwrite(str(out / "images" / name), bgr)
    pts_col = pts @ s[:3, :3].T + s[:3, 3]
    for p, tr in enumerate(tracks):
        if len(tr) >= 2:
            track = pycolmap.Track()
            for image_id, n in tr:
                track.add_element(image_id, n)
            rec.add_point3D(pts_col[p], track, rng.integers(0, 256, 3).astype(np.uint8))
    (out / "sparse").mkdir()
    rec.write_binary(str(out / "sparse"))
    return s, idx


def reprojection_px(rec, meta: dict, camera) -> np.ndarray:
    """Distance [px] of every observation of the pycolmap Reconstruction ``rec`` from its 3D
    point projected through ``camera`` (a dronecap Camera) at the pose the transforms.json
    ``meta`` gives the image (``images/NAME``, camera-to-world, OpenGL axes): float [n_obs]."""
    from dronecap.datasets.blender import opengl_to_opencv

    c2w = {
        f["file_path"]: opengl_to_opencv(np.array(f["transform_matrix"])) for f in meta["frames"]
    }
    errs = []
    for image in rec.images.values():
        pose = c2w[f"images/{image.name}"]
        obs = [p for p in image.points2D if p.has_point3D()]
        xyz = np.array([rec.points3D[p.point3D_id].xyz for p in obs]).reshape(-1, 3)
        uv = camera.project((xyz - pose[:3, 3]) @ pose[:3, :3])
        errs += list(np.hypot(*(uv - np.array([p.xy for p in obs]).reshape(-1, 2)).T))
    return np.array(errs)
