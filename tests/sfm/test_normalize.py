"""Scene normalisation and bounds on hand-made flights: up axis, robust box, near/far."""

from __future__ import annotations

import numpy as np
import pytest

from dronecap.datasets.normalize import (
    NormalizeSettings,
    apply_to_points,
    apply_to_poses,
    near_far,
    normalize_scene,
    rotation_between,
    up_rotation,
)


def corridor(n: int = 20, up=(0.0, 0.0, 1.0)) -> tuple[np.ndarray, np.ndarray]:
    """Cameras flying along world +x looking along +x, upright w.r.t. ``up``; wall points.

    Built z-up (camera axes: x right = -y world, y down = -z world, z forward = +x world), then
    turned so that world z becomes ``up``.
    """
    base = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])  # columns: x, y, z
    c2w = np.tile(np.eye(4), (n, 1, 1))
    c2w[:, :3, :3] = base
    c2w[:, 0, 3] = np.linspace(0, 10, n)  # 10 units along x, at height 1
    c2w[:, 2, 3] = 1.0
    rng = np.random.default_rng(0)
    pts = np.column_stack(
        [rng.uniform(0, 14, 600), rng.choice([-2.0, 2.0], 600), rng.uniform(0, 3, 600)]
    )
    pts = np.vstack([pts, [[500.0, 500.0, 500.0], [-300.0, 0.0, 40.0]]])  # two wild outliers
    turn = rotation_between(np.array([0.0, 0.0, 1.0]), np.asarray(up) / np.linalg.norm(up))
    c2w[:, :3, :3] = turn @ c2w[:, :3, :3]
    c2w[:, :3, 3] = c2w[:, :3, 3] @ turn.T
    return c2w, pts @ turn.T


def test_rotation_between_including_opposite_vectors():
    for a, b in [([1, 0, 0], [0, 1, 0]), ([0, 0, 1], [0, 0, -1]), ([1, 1, 0], [0, 0, 1])]:
        a = np.array(a, float) / np.linalg.norm(a)
        b = np.array(b, float) / np.linalg.norm(b)
        r = rotation_between(a, b)
        assert np.allclose(r @ a, b)
        assert np.allclose(r @ r.T, np.eye(3)) and np.linalg.det(r) == pytest.approx(1.0)


def test_up_rotation_maps_camera_up_to_z():
    c2w, _ = corridor(up=(1.0, 0.0, 0.0))  # the drone's "up" is world +x here
    r = up_rotation(c2w)
    assert np.allclose(r @ [1.0, 0.0, 0.0], [0.0, 0.0, 1.0])


@pytest.mark.parametrize("up", [(0.0, 0.0, 1.0), (0.0, 1.0, 0.0), (1.0, -1.0, 0.3)])
def test_normalize_scene_orients_centres_and_bounds_robustly(up):
    c2w, pts = corridor(up=up)
    norm = normalize_scene(c2w, pts)
    poses = apply_to_poses(norm.matrix, c2w)
    assert not norm.inliers[-2:].any()  # both wild points removed by the outlier filter
    # cameras are upright in the scene frame: their -y axis is +z
    assert np.allclose(-poses[:, :3, 1], [0.0, 0.0, 1.0], atol=1e-9)
    # the flight direction (longest spread) is along +-x
    travel = poses[-1, :3, 3] - poses[0, :3, 3]
    assert abs(travel[0]) == pytest.approx(np.linalg.norm(travel), rel=1e-3)  # within ~2 deg
    # box of the corridor before padding: x in [~0, ~14], y in [-2, 2], z in [~0, ~3]
    # -> longest half side 7 -> scale 1/7, so the camera track (10 units) spans 10/7
    assert np.linalg.norm(travel) == pytest.approx(10 / 7, rel=0.03)
    lo, hi = norm.aabb
    assert np.all(poses[:, :3, 3] > lo) and np.all(poses[:, :3, 3] < hi)
    # unit half side, padded on both ends by 5% of the longest side (2): 2 + 2 * 0.1
    assert np.max(hi - lo) == pytest.approx(2.2, rel=1e-9)
    kept = apply_to_points(norm.matrix, pts[norm.inliers])
    inside = np.all((kept > lo) & (kept < hi), axis=1).mean()
    assert inside > 0.95
    assert np.allclose(poses[:, :3, :3] @ poses[:, :3, :3].transpose(0, 2, 1), np.eye(3))


def test_normalize_scene_without_points_bounds_the_cameras():
    c2w, _ = corridor()
    norm = normalize_scene(c2w, np.zeros((0, 3)))
    poses = apply_to_poses(norm.matrix, c2w)
    lo, hi = norm.aabb
    assert np.all(hi > lo)  # the flat sides (one straight track) still have a thickness
    assert np.all(poses[:, :3, 3] > lo) and np.all(poses[:, :3, 3] < hi)


def test_near_far_tightens_to_observed_depths_within_the_box():
    # one camera at the origin looking along +z; box from z = 1 to z = 9
    c2w = np.eye(4)[None]
    aabb = np.array([[-1.0, -1.0, 1.0], [1.0, 1.0, 9.0]])
    z = np.linspace(3.0, 5.0, 101)
    seen = np.column_stack([np.zeros_like(z), np.zeros_like(z), z])
    nf = near_far(c2w, aabb, [seen])
    lo, hi = np.percentile(z, [1, 99])  # 3.02 and 4.98
    assert nf[0] == pytest.approx([0.5 * lo, 1.5 * hi])
    # too few observed points: the box's depth range
    nf = near_far(c2w, aabb, [seen[:3]], NormalizeSettings(min_view_points=8))
    assert nf[0] == pytest.approx([1.0, 9.0])


def test_statistical_inliers_drop_far_points_like_open3d():
    from dronecap.datasets.normalize import statistical_inliers

    rng = np.random.default_rng(3)
    pts = np.concatenate([rng.normal(0, 1, (400, 3)), [[30.0, 0, 0], [0, -25.0, 5]]])
    mask = statistical_inliers(pts, 16, 2.0)
    assert not mask[-2:].any() and mask[:400].mean() > 0.9
    o3d = pytest.importorskip("open3d", reason="open3d (the [sim] extra) gives the reference")
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts))
    _, keep = cloud.remove_statistical_outlier(nb_neighbors=16, std_ratio=2.0)
    ref = np.zeros(len(pts), bool)
    ref[np.asarray(keep)] = True
    assert (mask != ref).sum() <= 4  # same rule; open3d counts the point among its neighbours
