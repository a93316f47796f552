"""Camera rays and ray/AABB intersection, including the degenerate cases."""

import numpy as np
import torch

from dronecap.nerf.rays import camera_rays, ray_aabb

BOX = torch.tensor([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]])


def test_principal_ray_points_along_camera_z():
    c2w = torch.eye(4)
    c2w[:3, 3] = torch.tensor([0.0, 0.0, -5.0])
    # pixel (1, 1) of a 2x2 image with cx = cy = 1.5 has its centre exactly on the axis
    o, d = camera_rays(c2w, 10.0, 10.0, 1.5, 1.5, torch.tensor([1]), torch.tensor([1]))
    assert torch.allclose(d, torch.tensor([[0.0, 0.0, 1.0]]))
    assert torch.allclose(o, torch.tensor([[0.0, 0.0, -5.0]]))
    # one pixel to the right: x = 1/10 before normalisation (OpenCV: x right, y down)
    _, d2 = camera_rays(c2w, 10.0, 10.0, 1.5, 1.5, torch.tensor([2]), torch.tensor([1]))
    assert torch.allclose(d2, torch.tensor([[0.1, 0.0, 1.0]]) / np.sqrt(1.01))


def test_ray_hitting_box_from_outside():
    o = torch.tensor([[0.0, 0.0, -5.0]])
    d = torch.tensor([[0.0, 0.0, 1.0]])  # two exact zeros in the direction
    tn, tf, hit = ray_aabb(o, d, BOX)
    assert hit.item() and tn.item() == 4.0 and tf.item() == 6.0


def test_ray_missing_box_has_empty_segment():
    o = torch.tensor([[0.0, 3.0, -5.0]])
    d = torch.tensor([[0.0, 0.0, 1.0]])
    tn, tf, hit = ray_aabb(o, d, BOX)
    assert not hit.item() and tf.item() == tn.item()
    assert torch.isfinite(tn).all() and torch.isfinite(tf).all()


def test_ray_starting_inside_starts_at_zero():
    o = torch.tensor([[0.5, 0.0, 0.0]])
    d = torch.tensor([[1.0, 0.0, 0.0]])
    tn, tf, hit = ray_aabb(o, d, BOX)
    assert hit.item() and tn.item() == 0.0 and abs(tf.item() - 0.5) < 1e-6


def test_ray_pointing_away_from_box_misses():
    o = torch.tensor([[0.0, 0.0, 5.0]])
    d = torch.tensor([[0.0, 0.0, 1.0]])
    _, _, hit = ray_aabb(o, d, BOX)
    assert not hit.item()


def test_origin_on_face_and_ray_along_face_stay_finite():
    o = torch.tensor([[1.0, 0.0, 0.0], [1.0, 0.0, -3.0], [-1.0, -1.0, -1.0]])
    d = torch.tensor([[-1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [1.0, 1.0, 1.0]])
    d = d / d.norm(dim=-1, keepdim=True)
    tn, tf, hit = ray_aabb(o, d, BOX)
    assert torch.isfinite(tn).all() and torch.isfinite(tf).all()
    # on the +x face going inwards: crosses the whole box (length 2)
    assert hit[0] and tn[0] == 0.0 and abs(tf[0].item() - 2.0) < 1e-6
    # from a corner along the diagonal: length 2*sqrt(3)
    assert hit[2] and abs(tf[2].item() - 2 * np.sqrt(3)) < 1e-5
