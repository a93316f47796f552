"""Scene normalisation and bounds for a recovered flight: orient, centre, scale, AABB, near/far.

A drone flight looks outward along its path, so the "every camera looks at one point" centre
used for object captures does not apply. Instead:

1. **Up**: the mean of the cameras' up vectors (the -y column of each c2w, OpenCV axes) becomes
   +z of the scene frame (the NeRF Synthetic convention); the horizontal direction in which the
   sparse points spread most becomes +x, so the AABB is tight around a corridor-like flight.
2. **Centre and scale**: from the sparse points after statistical outlier removal (k-d tree) and
   per-axis percentiles, joined with the camera centres (rays start there); the box's centre
   moves to the origin and its longest half side to 1, so the scene fits [-1, 1]^3.
3. **Bounds**: the AABB (the robust box, padded) and per-view near/far from the depths of the
   points each view observes, kept inside the depth range of the AABB's corners.

The similarity applied is stored as a 4x4 matrix ``M``: x_scene = M @ x_colmap.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from dronecap.datasets.bounds import near_far_from_aabb


@dataclass
class NormalizeSettings:
    """Robust-statistics knobs of the normalisation (defaults suit a few hundred to 10^5 points)."""

    nb_neighbors: int = 16  # statistical outlier removal: neighbours considered
    std_ratio: float = 2.0  # ... and the distance threshold in standard deviations
    percentile: float = 1.0  # per-axis percentile (and 100 - it) that bounds the points
    margin: float = 0.05  # AABB padding, fraction of its longest side
    min_view_points: int = 8  # fewer observed points: the view's near/far come from the AABB


@dataclass
class Normalization:
    """The result: a similarity, the scene bounds, and which points counted."""

    matrix: np.ndarray  # float64 [4, 4], x_scene = matrix @ x_source (rotation * scale + shift)
    aabb: np.ndarray  # float64 [2, 3] in scene units
    inliers: np.ndarray  # bool [P], sparse points kept by the outlier removal


def up_rotation(c2w: np.ndarray) -> np.ndarray:
    """Rotation [3, 3] taking the mean camera up vector (-y of OpenCV cameras) to +z.

    Args:
        c2w: float64 [N, 4, 4] camera-to-world, OpenCV axes.

    Raises:
        ValueError: the up vectors cancel out (cameras rolled every which way).
    """
    up = -c2w[:, :3, 1].mean(0)
    norm = np.linalg.norm(up)
    if norm < 1e-6:
        raise ValueError("camera up vectors cancel out; no up direction")
    return rotation_between(up / norm, np.array([0.0, 0.0, 1.0]))


def rotation_between(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The smallest rotation [3, 3] taking unit vector ``a`` to unit vector ``b``."""
    v = np.cross(a, b)
    c = float(np.dot(a, b))
    if c < -1 + 1e-12:  # opposite: half-turn about any axis orthogonal to a
        axis = np.cross(a, [1.0, 0.0, 0.0] if abs(a[0]) < 0.9 else [0.0, 1.0, 0.0])
        axis /= np.linalg.norm(axis)
        return 2 * np.outer(axis, axis) - np.eye(3)
    vx = np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])
    return np.eye(3) + vx + vx @ vx / (1 + c)


def yaw_to_main_axis(points: np.ndarray) -> np.ndarray:
    """Rotation [3, 3] about z that turns the points' main horizontal spread onto +x.

    Args:
        points: float64 [P, 3], already z-up.
    """
    xy = points[:, :2] - points[:, :2].mean(0)
    if len(xy) < 2:
        return np.eye(3)
    w, v = np.linalg.eigh(xy.T @ xy)
    d = v[:, np.argmax(w)]
    ang = -np.arctan2(d[1], d[0])
    c, s = np.cos(ang), np.sin(ang)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def statistical_inliers(points: np.ndarray, nb_neighbors: int, std_ratio: float) -> np.ndarray:
    """Boolean [P] mask of the statistical outlier rule (all True when too few points).

    A point is an outlier when its mean distance to its ``nb_neighbors`` nearest neighbours
    exceeds the mean of that quantity over all points by more than ``std_ratio`` standard
    deviations (the rule of PCL's and open3d's statistical outlier removal; scipy's k-d tree
    does the search, so SfM needs no 3D-library install).
    """
    if len(points) <= nb_neighbors:
        return np.ones(len(points), bool)
    from scipy.spatial import cKDTree

    dist, _ = cKDTree(points).query(points, k=nb_neighbors + 1)  # column 0: the point itself
    mean_d = dist[:, 1:].mean(1)
    return mean_d <= mean_d.mean() + std_ratio * mean_d.std(ddof=1)


def robust_box(points: np.ndarray, percentile: float) -> np.ndarray:
    """Per-axis [percentile, 100 - percentile] box of points [P, 3] -> [2, 3]."""
    return np.percentile(points, [percentile, 100.0 - percentile], axis=0)


def normalize_scene(
    c2w: np.ndarray,
    points: np.ndarray,
    settings: NormalizeSettings | None = None,
    up: np.ndarray | None = None,
) -> Normalization:
    """Similarity and AABB for a flight (see the module docstring).

    Args:
        c2w: float64 [N, 4, 4] camera-to-world, OpenCV axes, SfM units.
        points: float64 [P, 3] sparse points, SfM units (may be empty).
        up: float64 [3] the known up direction in the input frame (e.g. +z of a world aligned
            to telemetry priors, opposite to gravity); None: the mean camera up vector.

    Returns:
        Normalization whose AABB contains every camera centre and the robust point box, with
        the longest half side of the unpadded box equal to 1.
    """
    st = settings or NormalizeSettings()
    if up is None:
        rot = up_rotation(c2w)
    else:
        rot = rotation_between(np.asarray(up, float) / np.linalg.norm(up), np.array([0, 0, 1.0]))
    inl = statistical_inliers(points, st.nb_neighbors, st.std_ratio)
    kept = points[inl] @ rot.T
    centres = c2w[:, :3, 3] @ rot.T
    rot = yaw_to_main_axis(kept if len(kept) >= 2 else centres) @ rot
    kept = points[inl] @ rot.T
    centres = c2w[:, :3, 3] @ rot.T
    parts = [centres]
    if len(kept):
        parts.append(robust_box(kept, st.percentile))
    allp = np.concatenate(parts)
    lo, hi = allp.min(0), allp.max(0)
    centre = (lo + hi) / 2
    half = float((hi - lo).max()) / 2
    scale = 1.0 / half if half > 0 else 1.0
    m = np.eye(4)
    m[:3, :3] = scale * rot
    m[:3, 3] = -scale * centre  # centre is already in the rotated frame
    lo_s, hi_s = scale * (lo - centre), scale * (hi - centre)
    pad = st.margin * float((hi_s - lo_s).max())
    # a flat side (e.g. one row of cameras and no points) still gets a positive thickness
    thickness = np.maximum(hi_s - lo_s, 0.0)
    extra = np.where(thickness < 2 * pad, pad, 0.0)
    aabb = np.stack([lo_s - pad - extra, hi_s + pad + extra])
    return Normalization(matrix=m, aabb=aabb, inliers=inl)


def apply_to_poses(m: np.ndarray, c2w: np.ndarray) -> np.ndarray:
    """Poses [N, 4, 4] after the similarity ``m`` (rotation columns stay orthonormal)."""
    scale = np.cbrt(np.linalg.det(m[:3, :3]))
    rot = m[:3, :3] / scale
    out = np.array(c2w, dtype=np.float64, copy=True)
    out[:, :3, :3] = rot @ out[:, :3, :3]
    out[:, :3, 3] = out[:, :3, 3] @ m[:3, :3].T + m[:3, 3]
    return out


def apply_to_points(m: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Points [P, 3] after the similarity ``m``."""
    return points @ m[:3, :3].T + m[:3, 3]


def near_far(
    c2w: np.ndarray,
    aabb: np.ndarray,
    view_points: list[np.ndarray],
    settings: NormalizeSettings | None = None,
) -> np.ndarray:
    """Per-view near/far [N, 2] in scene units.

    Args:
        c2w: float64 [N, 4, 4] normalised camera-to-world poses.
        aabb: float64 [2, 3] scene bounds.
        view_points: for each view, the [P_i, 3] normalised sparse points it observes.

    Near/far start from the depth range of the AABB's corners along the optical axis; a view that
    observes enough points tightens it to [0.5 x 1st percentile, 1.5 x 99th percentile] of their
    depths (never beyond the AABB's range).
    """
    st = settings or NormalizeSettings()
    box = near_far_from_aabb(c2w, aabb)
    out = box.copy()
    for i, pts in enumerate(view_points):
        if len(pts) < st.min_view_points:
            continue
        z = (pts - c2w[i, :3, 3]) @ c2w[i, :3, 2]
        z = z[z > 0]
        if len(z) < st.min_view_points:
            continue
        lo, hi = np.percentile(z, [1.0, 99.0])
        near = max(box[i, 0], 0.5 * lo)
        far = min(box[i, 1], 1.5 * hi)
        if far > near:
            out[i] = (near, far)
    return out
