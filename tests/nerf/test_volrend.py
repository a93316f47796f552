"""Packed volume rendering: hand-computed weights and the numerical extremes."""

import math

import pytest
import torch

from dronecap.nerf.volrend import packed_weights, render_packed


def _render(sigmas, t0, t1, ri, n_rays, colors, bg):
    def fn(a, b, r):
        return colors, sigmas

    return render_packed(t0, t1, ri, n_rays, fn, bg)


def test_two_rays_weights_by_hand():
    # ray 0: two samples of tau 1 and 2; ray 1: one sample of tau ln 2
    tau = torch.tensor([1.0, 2.0, math.log(2.0)])
    ri = torch.tensor([0, 0, 1])
    w, t = packed_weights(tau, ri, 2)
    expected_w = [1 - math.exp(-1), math.exp(-1) * (1 - math.exp(-2)), 0.5]
    assert torch.allclose(w, torch.tensor(expected_w), atol=1e-6)
    assert torch.allclose(t, torch.tensor([1.0, math.exp(-1), 1.0]), atol=1e-6)


def test_opaque_earlier_ray_does_not_disturb_later_rays():
    # ray 0 has enormous optical thickness; ray 1's transmittance must still be exact
    tau = torch.tensor([1e6 * 0.01] * 100 + [1e-3, 1e-3])
    ri = torch.tensor([0] * 100 + [1, 1])
    w, t = packed_weights(tau, ri, 2)
    assert t[100].item() == 1.0
    assert abs(t[101].item() - math.exp(-1e-3)) < 1e-7


@pytest.mark.parametrize("density", [0.0, 1e6])
@pytest.mark.parametrize("dt", [0.0, 0.01])
def test_extremes_finite_with_finite_gradients(density, dt):
    n = 8
    sig = torch.full((n,), density, requires_grad=True)
    col = torch.full((n, 2), 0.25, requires_grad=True)  # C = 2: nothing assumes RGB
    t0 = torch.arange(n, dtype=torch.float32) * dt
    ri = torch.zeros(n, dtype=torch.long)
    bg = torch.tensor([1.0, 0.0])
    rgb, opacity, depth = _render(sig, t0, t0 + dt, ri, 1, col, bg)
    (rgb.sum() + opacity.sum() + depth.sum()).backward()
    for x in (rgb, opacity, depth, sig.grad, col.grad):
        assert torch.isfinite(x).all()
    if density == 0.0 or dt == 0.0:  # all transparent: background only
        assert torch.allclose(rgb, bg[None]) and opacity.item() == 0.0
    else:  # all opaque: the first sample's colour
        assert torch.allclose(rgb, torch.tensor([[0.25, 0.25]])) and abs(opacity.item() - 1) < 1e-6


def test_empty_rays_render_background():
    bg = torch.tensor([[0.2], [0.7]])  # gray, per-ray background
    empty = torch.zeros(0)
    rgb, opacity, _ = _render(
        empty, empty, empty, torch.zeros(0, dtype=torch.long), 2, torch.zeros(0, 1), bg
    )
    assert torch.equal(rgb, bg) and torch.equal(opacity, torch.zeros(2))
