"""The trainer's optimizer step: a finiteness check and Adam, without the per-step bookkeeping
of ``torch.optim``.

``torch.optim.Adam(fused=True).step()`` spends about as long gathering its lists, grouping
tensors by device and dtype and incrementing each parameter's step counter as its fused kernel
spends updating the ~0.26 M parameters of the default model; and the trainer checked every
gradient for inf/NaN with one sum per tensor before it. :func:`step` makes the same update in
three calls: one pass over all gradients that flags a non-finite value
(``_amp_foreach_non_finite_check_and_unscale_`` with a scale of 1, the check of mixed-precision
training), one increment of the step counters and the fused kernel per parameter group. The
optimizer's state is torch's own (its first step runs through ``optimizer.step()``, which creates
it), so checkpoints save and load it as before.

With the C++ kernel (``csrc/adam.cpp``, passed as ``ext``) the check and the update are one
call each over all tensors together, torch's update in torch's order of operations: ~0.25
instead of ~0.4 ms for the default model at two threads (benchmarks/step_split.py).
"""

from __future__ import annotations

import torch

_ONE = torch.ones(1)


def step(optimizer: torch.optim.Adam, ext=None) -> bool:
    """One Adam update of the parameters that have gradients, unless a gradient holds an inf or
    a NaN; returns whether it stepped. A fused Adam (plain: no AMSGrad, maximize, capturable
    or decoupled weight decay) takes the direct path, any other ``optimizer.step()``; ``ext``
    is the C++ kernel (``nerf.backend.kernel("adam")``) or None (torch's fused Adam), used
    where every tensor is a contiguous float32 CPU one."""
    groups = [[p for p in g["params"] if p.grad is not None] for g in optimizer.param_groups]
    grads = [p.grad for ps in groups for p in ps]
    if not grads:
        return True
    ext = ext if ext is not None and all(_flat32(t) for t in grads) else None
    if not _finite(grads, ext):
        return False
    seen = all("step" in optimizer.state.get(p, {}) for ps in groups for p in ps)
    if not (seen and all(_plain(g) for g in optimizer.param_groups)):
        optimizer.step()  # torch creates the state of parameters it has not seen
        return True
    params = [p for ps in groups for p in ps]
    states = [optimizer.state[p] for p in params]
    moments = [st[k] for st in states for k in ("exp_avg", "exp_avg_sq")]
    kernel = ext is not None and all(_flat32(t) for t in (*params, *moments))
    _count_step(optimizer, states, add=not kernel)  # the kernel counts them itself
    if kernel:
        options = [(g["lr"], *g["betas"], g["weight_decay"], g["eps"])
                   for g, ps in zip(optimizer.param_groups, groups, strict=True)
                   for _ in ps]  # fmt: skip
        lrs, beta1s, beta2s, decays, eps = (list(column) for column in zip(*options, strict=True))
        ext.adam_step(params, grads, moments[0::2], moments[1::2], [st["step"] for st in states],
                      lrs, beta1s, beta2s, decays, eps)  # fmt: skip
        return True
    for group, params in zip(optimizer.param_groups, groups, strict=True):
        if not params:
            continue
        states = [optimizer.state[p] for p in params]
        steps = [s["step"] for s in states]
        beta1, beta2 = group["betas"]
        torch._fused_adam_(
            params, [p.grad for p in params], [s["exp_avg"] for s in states],
            [s["exp_avg_sq"] for s in states], [], steps, amsgrad=False, lr=group["lr"],
            beta1=beta1, beta2=beta2, weight_decay=group["weight_decay"], eps=group["eps"],
            maximize=False,
        )  # fmt: skip
    return True


def _finite(grads: list[torch.Tensor], ext) -> bool:
    """Whether every gradient is free of inf and NaN: one pass over them all (the C++ kernel's,
    or the check of torch's mixed-precision training with a scale of 1)."""
    if ext is not None:
        return bool(ext.all_finite(grads))
    found = torch.zeros(1, device=grads[0].device)
    torch._amp_foreach_non_finite_check_and_unscale_(grads, found, _ONE.to(found.device))
    return float(found) == 0.0


def _flat32(t: torch.Tensor) -> bool:
    """Whether the C++ kernel takes ``t``: contiguous float32 on the CPU."""
    return t.dtype == torch.float32 and t.device.type == "cpu" and t.is_contiguous()


def _plain(group: dict) -> bool:
    """Whether a parameter group is a fused Adam's without the options the direct path omits."""
    off = ("amsgrad", "maximize", "capturable", "differentiable", "decoupled_weight_decay")
    return bool(group.get("fused")) and not any(group.get(k) for k in off)


def _count_step(optimizer: torch.optim.Adam, stepping: list[dict], add: bool = True) -> None:
    """Add 1 to the step count in each of the ``stepping`` parameters' states (``add``; else
    only link or separate them, for the kernel that adds). While every parameter of
    ``optimizer`` steps, and their counts are equal, they share one count tensor (linked here
    on first sight, e.g. after a checkpoint load copied them apart), so that this is one
    scalar op instead of one per parameter; a step that leaves some out separates them
    again."""
    states = [optimizer.state.get(p, {}) for g in optimizer.param_groups for p in g["params"]]
    first = stepping[0]["step"]
    shared = all(s["step"] is first for s in stepping)  # linked already: no comparisons
    if len(stepping) == len(states) and (
        shared or all(torch.equal(s["step"], first) for s in stepping)
    ):
        for st in stepping:
            st["step"] = first
        if add:
            first.add_(1)
        return
    if len({id(st["step"]) for st in states if "step" in st}) < len(states):
        for st in states:  # some sit this step out: each its own count again
            if "step" in st:
                st["step"] = st["step"].clone()
    if add:
        torch._foreach_add_([st["step"] for st in stepping], 1)
