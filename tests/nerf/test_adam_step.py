"""The trainer's direct Adam step: torch's update, none with a non-finite gradient."""

import pytest
import torch

from dronecap.nerf import adam_step
from dronecap.nerf.backend import kernel


@pytest.fixture(params=["torch", "kernel"])
def ext(request):
    """None (torch's fused Adam) or the C++ kernel (skipped without a compiler)."""
    if request.param == "torch":
        return None
    k = kernel("adam")
    if k is None:
        pytest.skip("no C++ compiler: the Adam kernel is not built")
    return k


def _same(a: torch.Tensor, b: torch.Tensor, ext) -> None:
    """Equal bit for bit through torch; within float32 rounding through the kernel (its order
    of operations is torch's x86 build's: bit for bit there, not on every build)."""
    tol = {"rtol": 0, "atol": 0} if ext is None else {"rtol": 1e-6, "atol": 1e-12}
    torch.testing.assert_close(a, b, **tol)


def _model(seed: int = 0) -> list[torch.nn.Parameter]:
    """Three parameters; the last has enough elements for the kernel to split over threads."""
    g = torch.Generator().manual_seed(seed)
    shapes = ((500, 2), (16, 8), (20000, 2))
    return [torch.nn.Parameter(torch.randn(shape, generator=g)) for shape in shapes]


def _optimizer(params, **options) -> torch.optim.Adam:
    groups = [{"params": params[:1], "weight_decay": 0.0}, {"params": params[1:]}]
    return torch.optim.Adam(groups, lr=0.01, betas=(0.9, 0.99), eps=1e-15, **options)


def _set_grads(params, seed: int) -> None:
    g = torch.Generator().manual_seed(seed)
    for p in params:
        p.grad = torch.randn(p.shape, generator=g)


@pytest.mark.parametrize("options", [{"fused": True, "weight_decay": 1e-6}, {"amsgrad": True}])
def test_steps_as_torch_does(options, ext):
    a, b = _model(), _model()
    opt_a, opt_b = _optimizer(a, **options), _optimizer(b, **options)
    for k in range(4):
        _set_grads(a, k), _set_grads(b, k)
        assert adam_step.step(opt_a, ext)
        opt_b.step()
        for group in (*opt_a.param_groups, *opt_b.param_groups):
            group["lr"] *= 0.5  # a schedule: each step reads its group's lr
    for p, q in zip(a, b, strict=True):
        _same(p, q, ext)
        for key in ("exp_avg", "exp_avg_sq", "step"):
            _same(opt_a.state[p][key], opt_b.state[q][key], ext)


@pytest.mark.parametrize("bad", [float("nan"), float("inf"), -float("inf")])
def test_a_non_finite_gradient_changes_nothing(bad, ext):
    params = _model()
    opt = _optimizer(params, fused=True)
    _set_grads(params, 0)
    assert adam_step.step(opt, ext)
    before = [p.detach().clone() for p in params]
    state = {k: v.clone() for k, v in opt.state[params[0]].items()}
    _set_grads(params, 1)
    params[1].grad[3, 4] = bad
    assert not adam_step.step(opt, ext)
    assert all(torch.equal(p, q) for p, q in zip(params, before, strict=True))
    assert all(torch.equal(opt.state[params[0]][k], v) for k, v in state.items())
    _set_grads(params, 2)  # the next finite step goes on from there
    assert adam_step.step(opt, ext) and not torch.equal(params[0], before[0])


def test_counts_stay_per_parameter_through_skips_and_checkpoints(ext):
    a, b = _model(), _model()
    opt_a, opt_b = _optimizer(a, fused=True), _optimizer(b, fused=True)
    for k in range(5):
        _set_grads(a, k), _set_grads(b, k)
        if k == 2:  # the second parameter sits out a step: its count falls behind
            a[1].grad = b[1].grad = None
        if k == 3:  # a checkpoint: the state is copied out and back
            opt_a.load_state_dict(opt_a.state_dict())
        assert adam_step.step(opt_a, ext)
        opt_b.step()
    for p, q in zip(a, b, strict=True):
        _same(p, q, ext)
        assert float(opt_a.state[p]["step"]) == float(opt_b.state[q]["step"])
    assert [float(opt_a.state[p]["step"]) for p in a] == [5.0, 4.0, 5.0]
