"""What the dataset importers share: their options, reading and resizing posed images, and the
scene bounds.

Both ``import-transforms`` and ``import-colmap`` take, besides their source, ``out_path`` (the
``.h5`` written, atomically), ``size`` (the stored image width in pixels; the height keeps the
aspect ratio), ``color`` (``"auto"``, ``"rgb"`` or ``"gray"``, checked by
:func:`check_options`) and ``progress`` (a progress bar while reading images), and raise
:class:`InputError`, one line naming the file and what is wrong. Both end here:

- images: read with OpenCV (8- or 16-bit, gray, RGB or RGBA), area-resized to the stored width
  (height keeps the aspect ratio; colour premultiplied by alpha while resizing), stored RGB or
  BT.601 gray (:mod:`dronecap.datasets.blender`'s image helpers). ``color="auto"`` stores gray
  when every image is gray (single channel or R = G = B), so gray datasets round-trip exactly;
  alpha is kept (with a white background) when some pixel is not opaque; without alpha, frames
  whose borders are nearly all one colour (an object on a plain backdrop, as tools write RGB
  captures) declare that colour as the background (:mod:`dronecap.datasets.background`), camera
  footage none;
- the camera is scaled exactly through the resize (:meth:`Camera.scaled_to`: fx, cx by
  new width / old width, fy, cy by new height / old height; distortion unchanged);
- bounds as for a captured flight (:mod:`dronecap.datasets.normalize`): the poses are oriented,
  centred and scaled into [-1, 1]^3 from the sparse points and camera centres, the AABB is the
  robust box (or, for an object capture with alpha and a pinhole camera, carved from the masks as
  import-blender does), near/far come from the points each view observes — unless the source
  declares its own scene box, which is then kept with its poses unchanged.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from dronecap.datasets.format import Dataset, Intrinsics
from dronecap.errors import InputError

COLORS = ("auto", "rgb", "gray")
BACKGROUND = 1.0  # white, as import-blender


@dataclass
class Images:
    """Images read for a dataset."""

    images: np.ndarray  # uint8 [N, H, W, C]
    alpha: np.ndarray | None  # uint8 [N, H, W] or None when every pixel is opaque
    source_size: tuple[int, int]  # (width, height) of the files


def check_options(size: int, color: str) -> None:
    """Range-check ``size`` and ``color`` before any work."""
    if size < 8:
        raise InputError(f"size must be at least 8 pixels, got {size}")
    if color not in COLORS:
        raise InputError(f"unknown colour {color!r}: use one of {', '.join(COLORS)}")


def read_images(paths: list[Path], width: int, color: str, progress: bool = True) -> Images:
    """Read, resize and convert ``paths`` (see the module docstring).

    Raises:
        InputError: a missing or unreadable image, or images of different sizes.
    """
    from dronecap.datasets.blender import _read_rgba, _resize, _to_color
    from dronecap.progress import progress_bar

    rgbs, alphas, gray = [], [], True
    size = None
    for path in progress_bar(paths, desc="import", unit="img", disable=not progress):
        rgba = _read_rgba(path)
        if size is None:
            size = rgba.shape[:2]
        elif rgba.shape[:2] != size:
            raise InputError(
                f"image is {rgba.shape[1]}x{rgba.shape[0]}, the first is {size[1]}x{size[0]}",
                path,
            )
        gray &= bool((rgba[:, :, 0:2] == rgba[:, :, 1:3]).all())
        rgb, a = _resize(rgba, width)
        rgbs.append(rgb if color == "auto" else _to_color(rgb, color))  # uint8 once known
        alphas.append(a)
    if color == "auto":
        rgbs = [_to_color(rgb, "gray" if gray else "rgb") for rgb in rgbs]
    images = np.stack(rgbs)
    alpha = np.stack(alphas)
    return Images(images, None if (alpha == 255).all() else alpha, (size[1], size[0]))


def resized_camera(k: Intrinsics, images: np.ndarray) -> Intrinsics:
    """``k`` (for the source files) scaled exactly to the stored images' size."""
    h, w = images.shape[1:3]
    return k if (k.width, k.height) == (w, h) else k.scaled_to(w, h)


def visible_points(c2w: np.ndarray, k: Intrinsics, points: np.ndarray) -> list[np.ndarray]:
    """Row numbers of ``points`` [P, 3] in front of each camera and inside its image — the
    stand-in for "observed" when a source has points but no observations."""
    out = []
    for m in c2w:
        cam = (points - m[:3, 3]) @ m[:3, :3]
        front = cam[:, 2] > 1e-9
        idx = np.flatnonzero(front)
        if len(idx):
            uv = k.project(cam[idx])
            inside = (uv >= 0).all(1) & (uv[:, 0] < k.width) & (uv[:, 1] < k.height)
            idx = idx[inside]
        out.append(idx)
    return out


@dataclass
class Bounds:
    """Poses in the dataset's scene frame and its bounds."""

    poses: np.ndarray  # float64 [N, 4, 4] camera-to-world, OpenCV axes, scene frame
    points: np.ndarray  # float64 [P, 3] sparse points in the scene frame
    inliers: np.ndarray  # bool [P]: points kept by the outlier removal
    aabb: np.ndarray  # float64 [2, 3]
    near_far: np.ndarray  # float64 [N, 2]
    normalization: np.ndarray  # float64 [4, 4]: x_scene = M @ x_source
    bounds_from: str


def scene_bounds(
    c2w: np.ndarray,
    points: np.ndarray,
    seen: list[np.ndarray],
    keep_aabb: np.ndarray | None = None,
    masks: tuple[np.ndarray, Intrinsics, np.ndarray] | None = None,
    camera: Intrinsics | None = None,
    outer: tuple[np.ndarray, str] | None = None,
) -> Bounds:
    """Normalise and bound a posed scene as SfM does for a captured flight.

    Args:
        c2w: float64 [N, 4, 4] camera-to-world, OpenCV axes, source frame.
        points: float64 [P, 3] sparse points, source frame (may be empty).
        seen: for each view, the row numbers of the points it observes.
        keep_aabb: a scene box declared by the source: poses stay in the source frame and
            this is the AABB.
        masks: (alpha uint8 [M, H, W], a pinhole camera, the M view indices) of an object
            capture's training views: after the normalisation the AABB is carved from them as
            import-blender does (:func:`bounds.carve_aabb`) when carving bounds the object.
        camera: the stored camera; with it, a scene without sparse points is bounded by what
            its views cover (:func:`bounds.coverage_points`), never by the camera centres.
        outer: (a scene box the source declares as an outer limit, e.g. instant-ngp's
            ``aabb_scale`` box, its description): poses stay in the source frame and the AABB
            is what the views (or points) cover, clipped to it.

    Raises:
        InputError: cameras whose up vectors cancel out (no up direction to orient by).
    """
    from dronecap.datasets.bounds import coverage_points
    from dronecap.datasets.normalize import (
        NormalizeSettings,
        apply_to_points,
        apply_to_poses,
        near_far,
        normalize_scene,
        statistical_inliers,
    )

    if keep_aabb is not None:
        a = np.asarray(keep_aabb, float)
        st = NormalizeSettings()
        inl = statistical_inliers(points, st.nb_neighbors, st.std_ratio)
        nf = near_far(c2w, a, [points[s] for s in seen])
        return Bounds(c2w, points, inl, a, nf, np.eye(4), "the source's scene box")
    if outer is not None:
        return _inside_outer(c2w, points, seen, outer, camera)
    try:
        if not len(points) and camera is not None:
            cover, how = coverage_points(c2w, camera)
            norm = normalize_to(c2w, cover)
        else:
            norm = normalize_scene(c2w, points)
            how = "sparse points and cameras" if len(points) else "camera centres (no points)"
    except ValueError as err:
        raise InputError(f"cannot orient the scene: {err}") from None
    poses = apply_to_poses(norm.matrix, c2w)
    pts = apply_to_points(norm.matrix, points)
    aabb = norm.aabb
    if masks is not None:
        from dronecap.datasets.bounds import carve_aabb

        alpha, k, views = masks
        carved = carve_aabb(alpha, poses[views], k)
        if carved is not None:
            aabb, how = carved, "alpha carving"
    nf = near_far(poses, aabb, [pts[s] for s in seen])
    return Bounds(poses, pts, norm.inliers, aabb, nf, norm.matrix, how)


def normalize_to(c2w: np.ndarray, cover: np.ndarray) -> Any:
    """The similarity and AABB that bound the points ``cover`` [M, 3] (what the views cover),
    oriented as SfM orients a flight (up from the cameras, yaw to the points' main axis) and
    scaled to a longest half side of 1, with SfM's margin; camera centres are not added.

    Returns:
        :class:`dronecap.datasets.normalize.Normalization` (no sparse points, so no inliers).
    """
    from dronecap.datasets.normalize import (
        Normalization,
        NormalizeSettings,
        up_rotation,
        yaw_to_main_axis,
    )

    rot = up_rotation(c2w)
    rot = yaw_to_main_axis(cover @ rot.T) @ rot
    r = cover @ rot.T
    lo, hi = r.min(0), r.max(0)
    centre, half = (lo + hi) / 2, float((hi - lo).max()) / 2
    scale = 1.0 / half
    m = np.eye(4)
    m[:3, :3] = scale * rot
    m[:3, 3] = -scale * centre
    pad = NormalizeSettings().margin * 2.0
    aabb = np.stack([scale * (lo - centre) - pad, scale * (hi - centre) + pad])
    return Normalization(matrix=m, aabb=aabb, inliers=np.zeros(0, bool))


def _inside_outer(
    c2w: np.ndarray,
    points: np.ndarray,
    seen: list[np.ndarray],
    outer: tuple[np.ndarray, str],
    camera: Intrinsics | None,
) -> Bounds:
    """Bounds in the source frame: what the points (else the views) cover, clipped to the
    source's declared outer box (see :func:`scene_bounds`)."""
    from dronecap.datasets.bounds import coverage_points
    from dronecap.datasets.normalize import (
        NormalizeSettings,
        near_far,
        robust_box,
        statistical_inliers,
    )

    box, what = outer
    st = NormalizeSettings()
    inl = statistical_inliers(points, st.nb_neighbors, st.std_ratio)
    if inl.sum() >= st.min_view_points:
        cover, how = robust_box(points[inl], st.percentile), "sparse points"
    elif camera is not None:
        cover, how = coverage_points(c2w, camera)
    else:
        cover, how = box, what
    lo, hi = cover.min(0), cover.max(0)
    pad = st.margin * float((hi - lo).max())
    aabb = np.stack([np.maximum(lo - pad, box[0]), np.minimum(hi + pad, box[1])])
    if not (aabb[1] > aabb[0]).all():
        aabb, how = box, f"{what} (the views cover none of it)"
    else:
        how = f"{how}, inside {what}"
    nf = near_far(c2w, aabb, [points[s] for s in seen])
    return Bounds(c2w, points, inl, aabb, nf, np.eye(4), how)


def imported_dataset(
    imgs: Images,
    cameras: tuple[list[Intrinsics], np.ndarray],
    bounds: Bounds,
    names: list[str],
    split: np.ndarray,
    colors: np.ndarray | None,
    provenance: dict[str, Any],
    attrs: dict[str, Any],
    normalization: np.ndarray | None = None,
) -> Dataset:
    """The dataset (kind "dataset") an importer writes, one frame per image in source order.

    Args:
        imgs: the images as stored, with the size of the files.
        cameras: the distinct cameras of the files (resized here with the images) and each
            image's index among them, int64 [N]; the first is the dataset's camera, and with
            more than one every frame keeps its own.
        bounds: poses and bounds from :func:`scene_bounds`.
        names: [N] frame names.
        split: int8 [N] split codes.
        colors: uint8 [P, 3] colours of the bounds' points, or None (stored black).
        provenance: :func:`dronecap.datasets.format.provenance` of the import.
        attrs: the importer's own attributes ("source", counts); the source size, the source
            camera and what the bounds came from are added.
        normalization: [4, 4] source-to-scene transform when not the bounds' own.
    """
    table, index = cameras
    source_camera = table[0]
    inliers = bounds.inliers
    background, background_from = dataset_background(imgs)
    ds = Dataset(
        images=imgs.images,
        kind="dataset",
        alpha=imgs.alpha,
        poses=bounds.poses,
        intrinsics=resized_camera(source_camera, imgs.images),
        names=names,
        source_index=np.arange(len(names), dtype=np.int64),
        split=split,
        near_far=bounds.near_far,
        aabb=bounds.aabb,
        normalization=bounds.normalization if normalization is None else normalization,
        background=background,
        extra=points_extra(bounds.points[inliers], None if colors is None else colors[inliers]),
        provenance=provenance,
        attrs={
            **attrs,
            "source_size": list(imgs.source_size),
            "source_camera": dataclasses.asdict(source_camera),
            "bounds_from": bounds.bounds_from,
            "background_from": background_from,
        },
    )
    if len(table) > 1:
        ds.set_cameras([resized_camera(c, imgs.images) for c in table], index)
    return ds


def points_extra(points: np.ndarray, colors: np.ndarray | None) -> dict[str, np.ndarray]:
    """Dataset.extra entries of sparse points (see :mod:`dronecap.datasets.export_colmap`)."""
    from dronecap.datasets.export_colmap import POINTS_RGB, POINTS_XYZ

    if not len(points):
        return {}
    rgb = np.zeros((len(points), 3), np.uint8) if colors is None else colors
    return {POINTS_XYZ: np.asarray(points, np.float64), POINTS_RGB: np.asarray(rgb, np.uint8)}


def dataset_background(imgs: Images) -> tuple[tuple[float, ...] | None, str]:
    """The dataset background and where it came from: white when there is alpha, else the
    frames' plain backdrop when they have one (:func:`background.plain_background`), else
    None (camera footage)."""
    from dronecap.datasets.background import plain_background

    if imgs.alpha is not None:
        return (BACKGROUND,) * imgs.images.shape[3], "white behind the alpha channel"
    return plain_background(imgs.images)


def describe(path: Path) -> str:
    """Three lines on an imported dataset: views, size, split, camera; bounds; background."""
    from dronecap.datasets.format import open_dataset

    ds = open_dataset(path)
    counts = ", ".join(f"{len(ds.indices(s))} {s}" for s in ("train", "val", "test"))
    k = ds.intrinsics
    lo, hi = ds.aabb
    return (
        f"wrote {path}: {ds.n} views {ds.hw[1]}x{ds.hw[0]}x{ds.channels} ({counts}), camera "
        f"{k.model} fx={k.fx:.2f} fy={k.fy:.2f}\n"
        f"aabb {lo.round(3).tolist()} .. {hi.round(3).tolist()} ({ds.attrs['bounds_from']})\n"
        f"background: {ds.attrs.get('background_from', 'none')}"
    )
