"""Scene bounds from the data: an AABB carved from alpha masks, and per-view near/far.

The carving is a conservative visual hull on a voxel grid: a voxel survives when, in every view
that sees it, the disc its bounding sphere projects to touches an opaque pixel. It runs twice —
a coarse grid over a cube that encloses every camera, then a finer grid over what survived — and
the AABB is the box of the surviving voxels plus a small margin. Poses are camera-to-world in
OpenCV axes (x right, y down, z forward); intrinsics are in pixels with pixel centres at + 0.5.
"""

from __future__ import annotations

import numpy as np

from dronecap.datasets.format import Intrinsics

MIN_VIEWS = 2  # a voxel must be seen by at least this many views to count as evidence


def lookat_point(poses: np.ndarray) -> np.ndarray:
    """The point closest (least squares) to every camera's optical axis.

    Args:
        poses: float64 [N, 4, 4] camera-to-world, OpenCV axes (optical axis = +z column).

    Returns:
        float64 [3], scene units.
    """
    o = poses[:, :3, 3]
    d = poses[:, :3, 2] / np.linalg.norm(poses[:, :3, 2], axis=1, keepdims=True)
    proj = np.eye(3)[None] - d[:, :, None] * d[:, None, :]  # [N, 3, 3] projector off each axis
    a = proj.sum(0)
    b = np.einsum("nij,nj->i", proj, o)
    point, *_ = np.linalg.lstsq(a, b, rcond=None)
    return point


CONVERGED_SPREAD = 0.05  # smallest eigenvalue of the mean projector off the optical axes
FORWARD_DEPTH = 2.0  # depth seen by a forward capture without points, x its camera path extent


def view_centres(poses: np.ndarray, point: np.ndarray) -> np.ndarray:
    """Each camera's view centre: the point of its optical axis (in front of it) closest to
    ``point``.

    Args:
        poses: float64 [N, 4, 4] camera-to-world, OpenCV axes.
        point: float64 [3], e.g. :func:`lookat_point`.

    Returns:
        float64 [N, 3], scene units.
    """
    o = poses[:, :3, 3]
    d = poses[:, :3, 2] / np.linalg.norm(poses[:, :3, 2], axis=1, keepdims=True)
    t = np.maximum(((point - o) * d).sum(1), 0.0)
    return o + t[:, None] * d


def converging_point(poses: np.ndarray, intrinsics: Intrinsics) -> np.ndarray | None:
    """The look-at point when the optical axes converge on it, else None.

    They converge when the axes spread (the mean projector off the axes has no eigenvalue
    below ``CONVERGED_SPREAD``: parallel axes of a forward flight give ~0) and the point lies in
    front of at least half of the cameras, inside their images.
    """
    d = poses[:, :3, 2] / np.linalg.norm(poses[:, :3, 2], axis=1, keepdims=True)
    proj = np.eye(3)[None] - d[:, :, None] * d[:, None, :]
    if np.linalg.eigvalsh(proj.mean(0))[0] < CONVERGED_SPREAD:
        return None
    c = lookat_point(poses)
    cam = np.einsum("nji,nj->ni", poses[:, :3, :3], c - poses[:, :3, 3])  # [N, 3] camera axes
    k = intrinsics
    z = np.where(cam[:, 2] > 0, cam[:, 2], 1.0)
    u, v = k.fx * cam[:, 0] / z + k.cx, k.fy * cam[:, 1] / z + k.cy
    seen = (cam[:, 2] > 0) & (u >= 0) & (u < k.width) & (v >= 0) & (v < k.height)
    return c if seen.mean() >= 0.5 else None


def coverage_points(poses: np.ndarray, intrinsics: Intrinsics) -> tuple[np.ndarray, str]:
    """Points whose box is what the views cover, for a scene without sparse points.

    When the optical axes converge (:func:`converging_point`: an object capture), the corners of
    the look-at cube (:func:`lookat_cube`) and every camera's view centre; otherwise (a forward
    capture) the frusta from each camera centre to ``FORWARD_DEPTH`` times the extent of the
    camera path (the longest side of the camera centres' box): the corners of each frustum.

    Returns:
        (float64 [M, 3] points in the poses' frame, a phrase saying what they are).
    """
    c = converging_point(poses, intrinsics)
    if c is not None:
        cube = lookat_cube(poses, intrinsics)
        corners = np.stack(np.meshgrid(*cube.T, indexing="ij"), -1).reshape(8, 3)
        pts = np.concatenate([corners, view_centres(poses, c)])
        return pts, "where the view axes converge (look-at cube and view centres)"
    o = poses[:, :3, 3]
    extent = float((o.max(0) - o.min(0)).max())
    if extent <= 0:
        raise ValueError("the cameras neither converge on a point nor move")
    depth = FORWARD_DEPTH * extent
    k = intrinsics
    uv = np.array([[0, 0], [k.width, 0], [0, k.height], [k.width, k.height]], float)
    rays = np.concatenate([(uv - [k.cx, k.cy]) / [k.fx, k.fy], np.ones((4, 1))], 1)  # z = 1
    far = o[:, None] + depth * np.einsum("nij,kj->nki", poses[:, :3, :3], rays)  # [N, 4, 3]
    pts = np.concatenate([o, far.reshape(-1, 3)])
    return pts, f"the frusta to depth {FORWARD_DEPTH:g} x the camera path extent (forward capture)"


def lookat_cube(poses: np.ndarray, intrinsics: Intrinsics) -> np.ndarray:
    """Fallback bounds: the cube around the common look-at point that every camera sees.

    The cube's half-size is the radius of the largest sphere around the look-at point that fits
    inside every camera's field of view (distance × sin(half of the narrower field of view)).

    Returns:
        float64 [2, 3] (min, max), scene units.
    """
    c = lookat_point(poses)
    k = intrinsics
    half_fov = min(np.arctan(k.width / (2 * k.fx)), np.arctan(k.height / (2 * k.fy)))
    dist = np.linalg.norm(poses[:, :3, 3] - c, axis=1)
    r = float(dist.min() * np.sin(half_fov))
    return np.stack([c - r, c + r])


def carve_aabb(
    alpha: np.ndarray,
    poses: np.ndarray,
    intrinsics: Intrinsics,
    grid: int = 48,
    margin: float = 0.02,
    threshold: int = 0,
) -> np.ndarray | None:
    """AABB of the visual hull carved from alpha masks, or None when carving cannot bound it.

    Args:
        alpha: uint8 [N, H, W] coverage (255 opaque); pixels > ``threshold`` count as object.
        poses: float64 [N, 4, 4] camera-to-world, OpenCV axes.
        intrinsics: pinhole camera of the stored size.
        grid: voxels along the longest side of each of the two carving passes.
        margin: added on every side, as a fraction of the carved box's longest side.

    Returns:
        float64 [2, 3] (min, max) in scene units; None when nothing survives or the survivors
        touch the coarse region's border (masks carry no silhouette, e.g. fully opaque images).
    """
    import cv2

    masks = []
    for a in alpha:
        obj = a > threshold
        border = obj[0].any() or obj[-1].any() or obj[:, 0].any() or obj[:, -1].any()
        # distance (px) from each pixel to the nearest object pixel; 0 on the object
        masks.append((cv2.distanceTransform((~obj).astype(np.uint8), cv2.DIST_L2, 5), not border))
    w2c = np.linalg.inv(poses)[:, :3, :]
    c = lookat_point(poses)
    half = float(np.linalg.norm(poses[:, :3, 3] - c, axis=1).max())
    lo, hi = c - half, c + half
    box = _carve_pass(lo, hi, 2 * half / grid, masks, w2c, intrinsics, check_border=True)
    if box is None:
        return None
    coarse = 2 * half / grid
    lo, hi = box[0] - coarse, box[1] + coarse
    box = _carve_pass(lo, hi, float((hi - lo).max()) / grid, masks, w2c, intrinsics, False)
    if box is None:
        return None
    pad = margin * float((box[1] - box[0]).max())
    return np.stack([box[0] - pad, box[1] + pad])


def _carve_pass(
    lo: np.ndarray,
    hi: np.ndarray,
    voxel: float,
    masks: list[tuple[np.ndarray, bool]],
    w2c: np.ndarray,
    k: Intrinsics,
    check_border: bool,
) -> np.ndarray | None:
    """Carve a grid of cubic voxels of side ``voxel`` over [lo, hi]; box of the survivors.

    ``masks`` holds, per view, the distance map (px to the nearest object pixel) and whether the
    view sees the whole object (its silhouette does not touch the image border); such a view
    also carves what lies outside its frustum.
    """
    dims = np.maximum(np.ceil((hi - lo) / voxel).astype(int), 1)
    ijk = np.stack(np.meshgrid(*[np.arange(d) for d in dims], indexing="ij"), -1).reshape(-1, 3)
    centres = lo + voxel * (ijk + 0.5)
    radius = voxel * np.sqrt(3) / 2
    alive = np.arange(len(centres))  # indices of voxels not carved so far
    seen = np.zeros(len(centres), np.int32)
    for (dist, whole), m in zip(masks, w2c, strict=True):
        h, w = dist.shape
        p = centres[alive] @ m[:, :3].T + m[:, 3]
        z = p[:, 2]
        front = z > radius
        zs = np.where(front, z, 1.0)
        u = k.fx * p[:, 0] / zs + k.cx
        v = k.fy * p[:, 1] / zs + k.cy
        uc, vc = np.clip(u, 0, w - 1e-6), np.clip(v, 0, h - 1e-6)
        inside = front & (u == uc) & (v == vc)
        # lower bound of the distance from (u, v) to the nearest object pixel (for a point outside
        # the image: the way to the image border plus the distance from there)
        d = np.hypot(np.hypot(u - uc, v - vc), dist[vc.astype(int), uc.astype(int)])
        # radius of the bounding sphere's image, + 1 px for sampling the distance at a pixel centre
        r_px = k.fx * radius / np.sqrt(np.maximum(zs**2 - radius**2, 1e-12)) + 1.0
        hit = d <= r_px
        if whole:
            keep = np.where(front, hit, z >= -radius)
        else:
            keep = ~inside | hit
        seen[alive] += inside
        alive = alive[keep]
        if not len(alive):
            return None
    alive = alive[seen[alive] >= MIN_VIEWS]
    if not len(alive):
        return None
    kept = ijk[alive]
    if check_border and ((kept == 0).any() or (kept == dims - 1).any()):
        return None
    return np.stack([lo + voxel * kept.min(0), lo + voxel * (kept.max(0) + 1)])


def near_far_from_aabb(poses: np.ndarray, aabb: np.ndarray) -> np.ndarray:
    """Per-view near/far: depth range of the AABB's corners along each optical axis.

    Args:
        poses: float64 [N, 4, 4] camera-to-world, OpenCV axes.
        aabb: float64 [2, 3] (min, max).

    Returns:
        float64 [N, 2] (near, far) in scene units; near is at least 1e-3 × far (a camera inside
        the box starts sampling just in front of itself).
    """
    corners = np.stack(np.meshgrid(*aabb.T, indexing="ij"), -1).reshape(8, 3)
    rel = corners[None] - poses[:, None, :3, 3]  # [N, 8, 3]
    z = np.einsum("nkj,nj->nk", rel, poses[:, :3, 2])
    far = z.max(1)
    near = np.maximum(z.min(1), 1e-3 * far)
    return np.stack([near, far], -1)
