"""The Huber loss: torch's smooth L1 values, one autograd node, the same gradient by hand."""

import math

import pytest
import torch
import torch.nn.functional as F

from dronecap.nerf.backend import kernel
from dronecap.nerf.losses import HUBER_DELTA, huber_loss, huber_loss_and_grad, psnr_from_mse


def _march():
    """The marching kernel (its one-pass loss), or a skip without a compiler."""
    ext = kernel("march")
    if ext is None:
        pytest.skip("no C++ compiler: the kernel's loss is not built")
    return ext


def _pair():
    g = torch.Generator().manual_seed(0)
    pred = torch.rand(500, 3, generator=g)
    target = torch.rand(500, 3, generator=g)
    target[:4, 0] = pred[:4, 0] + torch.tensor([HUBER_DELTA, -HUBER_DELTA, 0.0, 1e-9])
    return pred, target


@pytest.mark.parametrize("cpp", [False, True], ids=["torch", "kernel"])
def test_the_loss_and_its_gradient_are_smooth_l1s_also_at_the_transition(cpp):
    ext = _march() if cpp else None
    pred, target = _pair()
    x = pred.clone().requires_grad_(True)
    ref = F.smooth_l1_loss(x, target, reduction="sum", beta=HUBER_DELTA) / 1500
    ref.backward()
    y = pred.clone().requires_grad_(True)
    loss = huber_loss(y, target, 1500, ext)
    loss.backward()
    torch.testing.assert_close(loss, ref.detach(), rtol=1e-6, atol=0)
    torch.testing.assert_close(y.grad, x.grad, rtol=1e-5, atol=1e-12)


@pytest.mark.parametrize("cpp", [False, True], ids=["torch", "kernel"])
def test_the_gradient_by_hand_is_autograds_bit_for_bit(cpp):
    ext = _march() if cpp else None
    pred, target = _pair()
    y = pred.clone().requires_grad_(True)
    (2.0 * huber_loss(y, target, 1500, ext)).backward()  # a factor from the rest of the graph
    loss, grad = huber_loss_and_grad(pred, target, 1500, ext)
    assert not loss.requires_grad and not grad.requires_grad
    assert torch.equal(2.0 * grad, y.grad)


def test_the_kernels_gradient_is_the_torch_ops_bit_for_bit():
    pred, target = _pair()
    target[4:8] = pred[4:8]  # d = 0 exactly: no gradient
    loss, grad = huber_loss_and_grad(pred, target, 1500, _march())
    ref_loss, ref_grad = huber_loss_and_grad(pred, target, 1500)
    assert torch.equal(grad, ref_grad) and not grad[4:8].any()
    torch.testing.assert_close(loss, ref_loss, rtol=1e-6, atol=0)  # the sum in double


@pytest.mark.parametrize("cpp", [False, True], ids=["torch", "kernel"])
@pytest.mark.parametrize("bad", [math.nan, math.inf])
def test_a_non_finite_colour_makes_the_loss_non_finite(bad, cpp):
    ext = _march() if cpp else None
    pred, target = torch.zeros(4, 3), torch.zeros(4, 3)
    pred[2, 1] = bad
    loss, _ = huber_loss_and_grad(pred, target, 12, ext)
    assert not math.isfinite(float(loss))  # the trainer then skips the step
    assert not math.isfinite(float(huber_loss(pred, target, 12, ext)))


def test_psnr_of_an_mse():
    assert psnr_from_mse(0.01) == pytest.approx(20.0)
    assert psnr_from_mse(0.0) == math.inf
