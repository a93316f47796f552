"""Packed volume rendering: hand-computed weights and the numerical extremes."""

import math

import pytest
import torch

from dronecap.nerf.backend import kernel
from dronecap.nerf.volrend import composite, distortion, packed_weights, render_packed


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
    rgb, opacity, depth, _ = _render(sig, t0, t0 + dt, ri, 1, col, bg)
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
    rgb, opacity, _, _ = _render(
        empty, empty, empty, torch.zeros(0, dtype=torch.long), 2, torch.zeros(0, 1), bg
    )
    assert torch.equal(rgb, bg) and torch.equal(opacity, torch.zeros(2))


def test_distortion_matches_the_double_sum_and_prefers_one_surface():
    """The O(S) form equals ``sum_ij w_i w_j |m_i - m_j| + 1/3 sum_i w_i^2 d_i`` per ray
    (rays of 3, 2, 1 and 0 samples), and weight spread along a ray costs more than the same
    weight in one interval."""
    gen = torch.Generator().manual_seed(0)
    ri = torch.tensor([0, 0, 0, 1, 1, 2])
    t0 = torch.tensor([0.1, 0.2, 0.5, 0.0, 0.3, 0.4])
    t1 = t0 + torch.tensor([0.1, 0.2, 0.1, 0.3, 0.1, 0.2])
    w = torch.rand(6, generator=gen)
    got = distortion(w, t0, t1, ri, 4)
    mid, width = (t0 + t1) / 2, t1 - t0
    for r in range(4):
        k = ri == r
        pairs = (w[k][:, None] * w[k][None] * (mid[k][:, None] - mid[k][None]).abs()).sum()
        assert abs(float(got[r]) - float(pairs + (w[k] ** 2 * width[k]).sum() / 3)) < 1e-6
    spread = distortion(torch.full((4,), 0.25), torch.arange(4.0), torch.arange(4.0) + 1,
                        torch.zeros(4, dtype=torch.long), 1)  # fmt: skip
    one = distortion(torch.tensor([1.0]), torch.tensor([0.0]), torch.tensor([1.0]),
                     torch.zeros(1, dtype=torch.long), 1)  # fmt: skip
    assert spread[0] > one[0]


def test_distortion_gradients_stay_finite_for_opaque_and_empty_rays():
    tau = torch.tensor([1e4, 1e4, 0.0, 0.0, 30.0], requires_grad=True)
    ri = torch.tensor([0, 0, 1, 1, 2])
    t0 = torch.tensor([0.0, 0.1, 0.0, 0.5, 0.2])
    w, _ = packed_weights(tau, ri, 3)
    d = distortion(w, t0, t0 + 0.1, ri, 3)
    d.sum().backward()
    assert torch.isfinite(d).all() and torch.isfinite(tau.grad).all()


def _packed(counts: list[int], seed: int = 0, scale: float = 1.0):
    g = torch.Generator().manual_seed(seed)
    ri = torch.repeat_interleave(torch.arange(len(counts)), torch.tensor(counts))
    t0 = torch.rand(ri.numel(), generator=g) * 2
    t1 = t0 + torch.rand(ri.numel(), generator=g) * 0.1
    sigma = torch.rand(ri.numel(), generator=g) * 20 * scale
    rgb = torch.rand(ri.numel(), 3, generator=g)
    bg = torch.rand(len(counts), 3, generator=g)
    return sigma, rgb, t0, t1, ri, bg


@pytest.mark.skipif(kernel("march", "auto") is None, reason="C++ kernel unavailable")
@pytest.mark.parametrize("scale", [0.0, 1.0, 1e3, 1e9])  # empty, fog, opaque, tau past 1e4
def test_composite_matches_render_packed_in_colour_and_gradients(scale):
    counts = [5, 0, 1, 40, 7, 0, 3]  # empty rays, one-sample rays, long rays
    sigma, rgb, t0, t1, ri, bg = _packed(counts, scale=scale)
    sigma[3] = float("nan")  # a NaN density counts as empty, as in packed_weights
    grads, colours = [], []
    for fused in (True, False):
        s, c, b = (x.clone().requires_grad_() for x in (sigma, rgb, bg))
        fn = lambda a, e, r, s=s, c=c: (c, s)  # noqa: E731
        if fused:
            out = composite(t0, t1, ri, len(counts), fn, b)
        else:
            out = render_packed(t0, t1, ri, len(counts), fn, b).color
        w = torch.randn(out.shape, generator=torch.Generator().manual_seed(1))
        (out * w).sum().backward()
        colours.append(out.detach())
        grads.append([s.grad, c.grad, b.grad])
    assert torch.allclose(colours[0], colours[1], atol=1e-6)
    for got, want in zip(*grads, strict=True):
        assert torch.isfinite(got).all()
        assert torch.allclose(got, want, rtol=1e-4, atol=1e-6 * max(1.0, float(want.abs().max())))


@pytest.mark.skipif(kernel("march", "auto") is None, reason="C++ kernel unavailable")
def test_composite_of_no_samples_is_the_background():
    bg = torch.rand(4, 3, requires_grad=True)
    empty = torch.zeros(0)
    out = composite(empty, empty, empty.long(), 4, lambda a, b, c: (torch.zeros(0, 3), empty), bg)
    assert torch.equal(out, bg.detach())
    out.sum().backward()
    assert torch.equal(bg.grad, torch.ones(4, 3))


@pytest.mark.skipif(kernel("march", "auto") is None, reason="C++ kernel unavailable")
def test_composite_on_two_threads_is_the_one_thread_result():
    counts = [5, 0, 1, 40, 7, 0, 3] * 150  # 8400 samples: the kernel splits them by rays
    sigma, rgb, t0, t1, ri, bg = _packed(counts)
    results = []
    before = torch.get_num_threads()
    try:
        for threads in (1, 2):
            torch.set_num_threads(threads)
            s, c, b = (x.clone().requires_grad_() for x in (sigma, rgb, bg))
            out = composite(t0, t1, ri, len(counts), lambda a, e, r, s=s, c=c: (c, s), b)
            (out * torch.linspace(-1, 1, out.numel()).reshape(out.shape)).sum().backward()
            results.append([out.detach(), s.grad, c.grad, b.grad])
    finally:
        torch.set_num_threads(before)
    for one, two in zip(*results, strict=True):
        assert torch.equal(one, two)
    with pytest.raises(RuntimeError, match="non-decreasing"):
        composite(t0, t1, ri.flip(0), len(counts), lambda a, e, r: (rgb, sigma), bg)
