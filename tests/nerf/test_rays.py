"""Camera rays (through the lens model, checked against OpenCV) and ray/AABB intersection."""

import cv2
import numpy as np
import pytest
import torch

from dronecap.camera import Camera
from dronecap.nerf.backend import kernel
from dronecap.nerf.rays import camera_rays, ray_aabb

BOX = torch.tensor([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]])


def test_principal_ray_points_along_camera_z():
    c2w = torch.eye(4)
    c2w[:3, 3] = torch.tensor([0.0, 0.0, -5.0])
    # pixel (1, 1) of a 3x3 image with cx = cy = 1.5 has its centre exactly on the axis
    cam = Camera(10.0, 10.0, 1.5, 1.5, 3, 3)
    o, d = camera_rays(c2w, cam, torch.tensor([1]), torch.tensor([1]))
    assert torch.allclose(d, torch.tensor([[0.0, 0.0, 1.0]]))
    assert torch.allclose(o, torch.tensor([[0.0, 0.0, -5.0]]))
    # one pixel to the right: x = 1/10 before normalisation (OpenCV: x right, y down)
    _, d2 = camera_rays(c2w, cam, torch.tensor([2]), torch.tensor([1]))
    assert torch.allclose(d2, torch.tensor([[0.1, 0.0, 1.0]]) / np.sqrt(1.01))


def _rotation(rx: float, ry: float, rz: float) -> np.ndarray:
    return cv2.Rodrigues(np.array([rx, ry, rz], np.float64))[0]


# published AI-deck-like lenses at 160x160 and stronger ones, each model OpenCV handles
LENSES = [
    Camera(183.0, 185.0, 84.0, 70.0, 160, 160, "SIMPLE_RADIAL", (-0.09,)),
    Camera(150.0, 150.0, 80.0, 80.0, 160, 160, "RADIAL", (-0.2, 0.05)),
    Camera(160.0, 158.0, 78.5, 83.0, 160, 120, "OPENCV", (-0.15, 0.03, 0.002, -0.001)),
    Camera(90.0, 90.0, 80.0, 80.0, 160, 160, "OPENCV_FISHEYE", (0.05, -0.01, 0.002, 0.0)),
]


@pytest.mark.parametrize("cam", LENSES, ids=lambda c: c.model)
def test_rays_through_the_corners_project_back_through_opencv(cam):
    """A point along the ray through pixel (u, v) projects (cv2.projectPoints with the world
    pose as rvec/tvec, or cv2.fisheye.projectPoints) onto (u + 0.5, v + 0.5)."""
    rot = _rotation(0.3, -0.2, 0.1)
    c2w = np.eye(4)
    c2w[:3, :3], c2w[:3, 3] = rot, [0.5, -1.0, 2.0]
    u = np.array([0, cam.width - 1, 0, cam.width - 1, cam.width // 2])
    v = np.array([0, 0, cam.height - 1, cam.height - 1, cam.height // 3])
    o, d = camera_rays(torch.as_tensor(c2w), cam, torch.as_tensor(u), torch.as_tensor(v))
    world = (o + 3.7 * d).double().numpy()
    w2c_r, w2c_t = rot.T, -rot.T @ c2w[:3, 3]
    rvec = cv2.Rodrigues(w2c_r)[0]
    pts = world.reshape(-1, 1, 3)
    if cam.is_fisheye:
        uv, _ = cv2.fisheye.projectPoints(pts, rvec, w2c_t, cam.matrix(), cam.opencv_coeffs())
    else:
        uv, _ = cv2.projectPoints(pts, rvec, w2c_t, cam.matrix(), cam.opencv_coeffs())
    expected = np.stack([u + 0.5, v + 0.5], 1)
    # float32 rays 3.7 units long: ~1e-6 relative, far below the 1e-3 px asked
    np.testing.assert_allclose(uv.reshape(-1, 2), expected, atol=1e-3, rtol=0)
    # and the lens matters: a pinhole ray through a corner lands pixels away
    if cam.model != "OPENCV_FISHEYE":
        o2, d2 = camera_rays(torch.as_tensor(c2w), cam.pinhole(), torch.as_tensor(u[:1]),
                             torch.as_tensor(v[:1]))  # fmt: skip
        uv2, _ = cv2.projectPoints((o2 + 3.7 * d2).double().numpy().reshape(-1, 1, 3), rvec,
                                   w2c_t, cam.matrix(), cam.opencv_coeffs())  # fmt: skip
        assert np.linalg.norm(uv2.reshape(2) - expected[0]) > 1.0


@pytest.mark.parametrize("backend", ["torch", "auto"])
def test_ray_hitting_box_from_outside(backend):
    o = torch.tensor([[0.0, 0.0, -5.0]])
    d = torch.tensor([[0.0, 0.0, 1.0]])  # two exact zeros in the direction
    tn, tf, hit = ray_aabb(o, d, BOX, backend)
    assert hit.item() and tn.item() == 4.0 and tf.item() == 6.0


@pytest.mark.parametrize("backend", ["torch", "auto"])
def test_ray_missing_box_has_empty_segment(backend):
    o = torch.tensor([[0.0, 3.0, -5.0]])
    d = torch.tensor([[0.0, 0.0, 1.0]])
    tn, tf, hit = ray_aabb(o, d, BOX, backend)
    assert not hit.item() and tf.item() == tn.item()
    assert torch.isfinite(tn).all() and torch.isfinite(tf).all()


@pytest.mark.parametrize("backend", ["torch", "auto"])
def test_ray_starting_inside_starts_at_zero(backend):
    o = torch.tensor([[0.5, 0.0, 0.0]])
    d = torch.tensor([[1.0, 0.0, 0.0]])
    tn, tf, hit = ray_aabb(o, d, BOX, backend)
    assert hit.item() and tn.item() == 0.0 and abs(tf.item() - 0.5) < 1e-6


@pytest.mark.parametrize("backend", ["torch", "auto"])
def test_ray_pointing_away_from_box_misses(backend):
    o = torch.tensor([[0.0, 0.0, 5.0]])
    d = torch.tensor([[0.0, 0.0, 1.0]])
    _, _, hit = ray_aabb(o, d, BOX, backend)
    assert not hit.item()


@pytest.mark.parametrize("backend", ["torch", "auto"])
def test_origin_on_face_and_ray_along_face_stay_finite(backend):
    o = torch.tensor([[1.0, 0.0, 0.0], [1.0, 0.0, -3.0], [-1.0, -1.0, -1.0]])
    d = torch.tensor([[-1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [1.0, 1.0, 1.0]])
    d = d / d.norm(dim=-1, keepdim=True)
    tn, tf, hit = ray_aabb(o, d, BOX, backend)
    assert torch.isfinite(tn).all() and torch.isfinite(tf).all()
    # on the +x face going inwards: crosses the whole box (length 2)
    assert hit[0] and tn[0] == 0.0 and abs(tf[0].item() - 2.0) < 1e-6
    # from a corner along the diagonal: length 2*sqrt(3)
    assert hit[2] and abs(tf[2].item() - 2 * np.sqrt(3)) < 1e-5


@pytest.mark.skipif(kernel("march", "auto") is None, reason="C++ marching kernel unavailable")
def test_the_kernel_slab_test_gives_the_torch_values_bit_for_bit():
    g = torch.Generator().manual_seed(3)
    o = torch.randn(4000, 3, generator=g) * 2
    d = torch.randn(4000, 3, generator=g)
    d[::7, 0] = 0.0  # parallel to a slab: inside it or not
    d[::11, 1] = -0.0
    d[::13] = d[::13] * 1e-13  # every component below TINY
    o[5, 2] = float("nan")  # NaN goes through as torch's ops pass it
    box = torch.tensor([[-1.0, -0.5, -2.0], [1.5, 0.5, 0.25]])
    for a, b in zip(ray_aabb(o, d, box, "auto"), ray_aabb(o, d, box, "torch"), strict=True):
        assert a.dtype == b.dtype and torch.equal(a.isnan(), b.isnan())
        assert torch.equal(a.nan_to_num(), b.nan_to_num())
