"""Multiresolution hash encoding (Instant-NGP) with a slow reference and a fast C++ kernel.

Conventions (the C++ kernel in ``csrc/hashgrid.cpp`` follows the same ones exactly):

- Level ``l`` has ``res_l`` cells per axis (:func:`nerf.levels.level_resolutions`, the formula
  shared with the GAP9 cost model); its corner grid has ``res_l + 1`` points per axis.
- A point ``x`` in ``[0, 1]^3`` (coordinates outside are clamped, NaN counts as 0) is scaled to
  ``p = x * res_l`` with **no** +0.5 offset, so the faces ``x = 0`` and ``x = 1`` fall exactly on
  grid corners. Its cell is ``i = min(floor(p), res_l - 1)`` per axis (so ``x = 1`` lies in the
  last cell with weight 1 on the far corner) and its weights are the trilinear ones of
  ``f = p - i``.
- Corner ``c`` of level ``l`` reads row ``offsets[l] + index(c)`` of ``table``:
  dense ``c0 + c1 (res+1) + c2 (res+1)^2`` when ``(res+1)^3 <= T = 2**log2_hashmap``, else the
  spatial hash ``(c0 * 1 ^ c1 * 2654435761 ^ c2 * 805459861) mod T`` (int64 here; the C++ kernel
  uses uint32 wrap-around, which gives the same result because ``T`` is a power of two).
- Output ``[N, L * F]``, level-major: columns ``l*F:(l+1)*F`` hold level ``l``.

Low-precision storage (``dtype=torch.float16`` / ``torch.bfloat16``) is emulated: the parameter
stays a float32 master copy, the encoding reads it rounded to ``dtype`` (straight-through
gradient; values beyond the dtype's range saturate to its largest finite value), and
:meth:`HashGrid.round_storage_` rounds the master in place (call it after each
optimizer step to emulate pure low-precision storage, where updates below half an ulp are lost).
"""

from __future__ import annotations

import functools
from collections.abc import Sequence
from typing import NamedTuple

import torch
from torch import Tensor

from .backend import check_backend, kernel
from .backend import load as backend_load
from .kernel_args import f32, i64
from .levels import level_offsets, level_resolutions

__all__ = [
    "HashGrid",
    "hash_encode_cpp",
    "hash_encode_reference",
    "level_offsets",
    "level_resolutions",
    "load_extension",
]

PRIMES = (1, 2654435761, 805459861)


def _corner_bits(device: torch.device) -> Tensor:
    """The 8 cell corners as 0/1 offsets, shape [8, 3] int64 (bit k of the corner id = axis k)."""
    ids = torch.arange(8, device=device)
    return torch.stack([(ids >> k) & 1 for k in range(3)], dim=-1)


def _clamp_unit(x: Tensor) -> Tensor:
    """Float32 positions clamped to [0, 1]^3; NaN -> 0, +inf -> 1, -inf -> 0. Shape kept."""
    return torch.nan_to_num(x.float(), nan=0.0, posinf=1.0, neginf=0.0).clamp(0.0, 1.0)


def hash_encode_reference(
    x: Tensor,
    table: Tensor,
    resolutions: Sequence[int],
    offsets: Sequence[int],
    log2_hashmap: int,
) -> Tensor:
    """The slow, obvious hash encoding: trilinear blend of 8 gathered corners per level.

    Args:
        x: [N, 3] positions in the unit cube (clamped; NaN -> 0).
        table: [offsets[-1], F] feature rows (any float dtype; math in float32).
        resolutions: cells per axis of each level (L values).
        offsets: start row of each level, L + 1 values.
        log2_hashmap: log2 of T, the maximum rows per level.
    Returns:
        [N, L * F] float32 features, level-major. Differentiable w.r.t. ``table`` only.
    """
    x = _clamp_unit(x)
    table = table.float()
    bits = _corner_bits(x.device)  # [8, 3]
    primes = torch.tensor(PRIMES, dtype=torch.int64, device=x.device)
    max_rows = 1 << log2_hashmap
    out = []
    for lvl, res in enumerate(resolutions):
        pos = x * res
        cell = pos.floor().clamp(max=res - 1)
        frac = pos - cell  # [N, 3] in [0, 1]
        corner = cell.long()[:, None, :] + bits  # [N, 8, 3]
        if (res + 1) ** 3 <= max_rows:
            index = corner[..., 0] + corner[..., 1] * (res + 1) + corner[..., 2] * (res + 1) ** 2
        else:
            h = corner * primes
            index = (h[..., 0] ^ h[..., 1] ^ h[..., 2]) % (offsets[lvl + 1] - offsets[lvl])
        weight = torch.where(bits.bool(), frac[:, None, :], 1.0 - frac[:, None, :]).prod(-1)
        rows = table[offsets[lvl] + index]  # [N, 8, F]
        out.append((weight[..., None] * rows).sum(dim=1))
    return torch.cat(out, dim=-1)


class _RoundTo(torch.autograd.Function):
    """Round a tensor to a storage dtype and back to float32; straight-through gradient."""

    @staticmethod
    def forward(ctx, t: Tensor, dtype: torch.dtype) -> Tensor:  # noqa: D102
        limit = torch.finfo(dtype).max  # saturate: stored values are never inf
        return t.clamp(-limit, limit).to(dtype).float()

    @staticmethod
    def backward(ctx, grad: Tensor) -> tuple[Tensor, None]:  # noqa: D102
        return grad, None


class Visible(NamedTuple):
    """The samples compaction's pre-pass keeps (:meth:`HashGrid.fused_visible`), in order."""

    ray_indices: Tensor  # int64 [K]
    t_starts: Tensor  # float32 [K] scene units
    t_ends: Tensor  # float32 [K]
    counts: Tensor  # int64 [R] kept samples of each ray
    encoded: Tensor  # float32 [K, levels * features] their hash encodings
    unit: Tensor  # float32 [K, 3] their midpoints in the box's unit cube (what was encoded)
    found: int  # the samples kept before a batch's cut (K without one)


class HashGrid(torch.nn.Module):
    """Instant-NGP multiresolution hash encoding of points in the unit cube.

    Args:
        levels: L, number of resolution levels.
        features: F, features per level and table row.
        log2_hashmap: log2 of T, the maximum rows per level.
        n_min, n_max: cells per axis of the coarsest and finest levels.
        backend: "auto" (C++ kernel, falling back to "torch" with a one-time notice), "cpp",
            "compile" (torch.compile of the reference) or "torch" (the reference); see
            :func:`nerf.backend.kernel`.
        dtype: storage precision of the table (float32, float16 or bfloat16; emulated, see the
            module docstring).
        inplace_grad: with the C++ kernel, add the table gradient straight into
            ``table.grad`` instead of returning a full-size gradient per call (saves a
            temporary and an addition per call when a step accumulates several tiles; autograd
            then sees no gradient for the table: use ``loss.backward()``, not
            ``torch.autograd.grad``).
    """

    def __init__(
        self,
        levels: int,
        features: int,
        log2_hashmap: int,
        n_min: int,
        n_max: int,
        backend: str = "auto",
        dtype: torch.dtype = torch.float32,
        inplace_grad: bool = False,
    ) -> None:
        super().__init__()
        check_backend(backend)
        if dtype not in (torch.float32, torch.float16, torch.bfloat16):
            raise ValueError(f"dtype must be float32, float16 or bfloat16, got {dtype}")
        self.levels = levels
        self.features = features
        self.log2_hashmap = log2_hashmap
        self.resolutions = level_resolutions(levels, n_min, n_max)
        self.offsets = level_offsets(self.resolutions, log2_hashmap)
        self.out_dim = levels * features
        self.dtype = dtype
        self.backend = backend
        self.inplace_grad = inplace_grad
        table = torch.empty(self.offsets[-1], features).uniform_(-1e-4, 1e-4)
        self.table = torch.nn.Parameter(table)
        self._encode = None  # resolved lazily on first forward

    def _resolve(self):
        """Pick the encoding function for ``self.backend`` (the fallback rule of
        :func:`nerf.backend.kernel`; compiles the C++ kernel if needed)."""
        if kernel("hashgrid", self.backend) is not None:
            if self.inplace_grad:
                return functools.partial(hash_encode_cpp, grad_into=self.table)
            return hash_encode_cpp
        if self.backend == "compile":
            return _compiled_reference()
        return hash_encode_reference

    def prepare(self) -> None:
        """Resolve the encoding function now (building the C++ kernel if needed) instead of at
        the first forward."""
        if self._encode is None:
            self._encode = self._resolve()

    def forward(self, x: Tensor, cached: Tensor | None = None) -> Tensor:
        """Encode ``x`` [N, 3] (unit cube, clamped) into [N, levels * features] float32.

        ``cached``: this very encoding of ``x``, computed earlier without autograd (a training
        pass after :mod:`.compaction`); with the C++ kernel it is returned as the result and
        only the backward runs, other backends compute the encoding again.
        """
        self.prepare()
        table = (
            self.table if self.dtype == torch.float32 else _RoundTo.apply(self.table, self.dtype)
        )
        args = (x, table, self.resolutions, self.offsets, self.log2_hashmap)
        if cached is not None and kernel("hashgrid", self.backend) is not None:
            return self._encode(*args, cached=cached)
        return self._encode(*args)

    @torch.no_grad()
    def fused_density(
        self, x: Tensor, w1: Tensor, w2: Tensor, keep_encoded: bool, bf16: bool = False
    ) -> tuple[Tensor, Tensor | None] | None:
        """The encoding of ``x`` [N, 3] (unit cube) run through a one-hidden-layer ReLU MLP in
        one C++ pass, without autograd; None when the C++ kernel is not in use or the table is
        not stored in float32 (then encode and multiply separately).

        Args:
            w1: [hidden, levels * features] the hidden layer's weight (bias-free).
            w2: [hidden] the output row wanted (the density's, before its activation).
            keep_encoded: also return the encoding [N, levels * features] (as :meth:`forward`).
            bf16: the hidden layer multiplies bf16-rounded encodings on the AMX tiles (float32
                sums, ReLU and output row) where the kernel has them, else in float32.

        Returns:
            (raw [N] = w2 . relu(w1 @ encoding), encoding or None), float32. Blocks of points
            are encoded and multiplied while they are in cache: the [N, hidden] activations
            are never written (compaction's pre-pass and the occupancy updates query ~20-50k
            points a step).
        """
        if not self._fusable():
            return None
        raw, encoded = load_extension().density(
            x.float().contiguous(), *self._table_args(), w1.detach().float(), w2.detach().float(),
            keep_encoded, bf16,
        )  # fmt: skip
        return raw, (encoded if keep_encoded else None)

    @torch.no_grad()
    def fused_visible(
        self, rays: tuple[Tensor, Tensor, Tensor], samples: tuple[Tensor, Tensor, Tensor],
        w1: Tensor, w2: Tensor, max_log_density: float, min_transmittance: float,
        bf16: bool = False, max_kept: int = 0,
    ) -> Visible | None:  # fmt: skip
        """Compaction's pre-pass in one C++ call (None as :meth:`fused_density`): the density
        exp(clamp(w2 . relu(w1 @ encoding), +-max_log_density)) of packed samples at their
        midpoints, each ray's transmittance before each sample (as
        :func:`nerf.volrend.packed_weights`), and the samples where it is above
        ``min_transmittance``. Rays march front to back and stop at their cut: samples behind
        it are mostly never encoded.

        Args:
            rays: (origins [R, 3], directions [R, 3], box [2, 3]: the min corner and size of the
                box whose unit cube is encoded), scene units.
            samples: (t_starts [S], t_ends [S] scene units, ray_indices [S] int64 non-decreasing).
            w1, w2, bf16: as in :meth:`fused_density`.

        Returns:
            the kept samples (:class:`Visible`), with the kept count of each of the R rays.
        """
        if not self._fusable():
            return None
        origins, dirs, box = (f32(t) for t in rays)
        t0, t1, ri = samples
        kept, found = load_extension().visible(
            origins, dirs, f32(t0), f32(t1), i64(ri), box, *self._table_args(),
            f32(w1), f32(w2), max_log_density, min_transmittance, bf16, max_kept,
        )  # fmt: skip
        return Visible(*kept, found)

    @torch.no_grad()
    def fused_grid_refresh(
        self, grid: tuple, cells: Tensor, jitter: Tensor, box: Tensor, density_mlp: tuple,
        bf16: bool = False,
    ) -> tuple[Tensor, Tensor] | None:  # fmt: skip
        """An occupancy-grid update after its draws in one C++ call (None as
        :meth:`fused_density`): each sampled cell's density at its jittered point, as
        :meth:`fused_density` computes it, folded into the grid.

        Args:
            grid: (density float32 [R^3], allowed bool [R^3] or None, aabb [2, 3] of the grid,
                R, step_size, decay, threshold) as :func:`nerf.occupancy.update` has them.
            cells, jitter: [M] flat cell indices and [M, 3] positions in [0, 1) inside them.
            box: [2, 3] the min corner and size of the box whose unit cube is encoded.
            density_mlp: (w1, w2, max_log_density) as in :meth:`fused_visible`.

        Returns:
            the new (density, occupied) of :func:`nerf.occupancy.update`.
        """
        if not self._fusable():
            return None
        density, allowed, aabb, res, step_size, decay, threshold = grid
        w1, w2, lim = density_mlp
        ok = torch.zeros(0, dtype=torch.bool) if allowed is None else allowed.contiguous()
        return tuple(load_extension().grid_refresh(
            density.float(), ok, cells.long(), jitter.float(), aabb.float(), box.float(),
            int(res), float(step_size), float(decay), float(threshold), *self._table_args(),
            w1.detach().float(), w2.detach().float(), float(lim), bf16,
        ))  # fmt: skip

    def backward_args(self) -> tuple | None:
        """The table layout :func:`table_backward` takes for this table (the backward of
        :meth:`forward`), or None where that is not the backward in use (not the C++ kernel,
        or a table stored below float32)."""
        self.prepare()
        if not self._fusable():
            return None
        rows, features = self.table.shape
        level = BACKWARD_MODES["level"]
        return rows, features, list(self.resolutions), list(self.offsets), self.log2_hashmap, level

    def _fusable(self) -> bool:
        """Whether the fused C++ queries can run: float32 storage and the C++ kernel."""
        return self.dtype == torch.float32 and kernel("hashgrid", self.backend) is not None

    def _table_args(self) -> tuple:
        """The table and level layout as the C++ kernels take them."""
        table = f32(self.table)
        return table, self.resolutions, self.offsets, self.log2_hashmap

    @torch.no_grad()
    def round_storage_(self) -> None:
        """Round the float32 master table in place to the storage dtype (no-op for float32)."""
        if self.dtype != torch.float32:
            self.table.copy_(_RoundTo.apply(self.table, self.dtype))

    def extra_repr(self) -> str:  # noqa: D102
        return (
            f"levels={self.levels}, features={self.features}, log2_hashmap={self.log2_hashmap}, "
            f"resolutions={self.resolutions[0]}..{self.resolutions[-1]}, backend={self.backend}, "
            f"dtype={self.dtype}"
        )


def load_extension():
    """The hash encoding kernels (``csrc/hashgrid.cpp``), built on first use (:mod:`.backend`)."""
    return backend_load("hashgrid")


BACKWARD_MODES = {"level": 0, "atomic": 1, "partial": 2}


class _CppEncode(torch.autograd.Function):
    """Autograd wrapper of the C++ kernels; gradient w.r.t. the table only.

    With ``grad_into`` (a float32 leaf parameter), the backward adds the table gradient straight
    into ``grad_into.grad`` and hands autograd no gradient for ``table``.
    """

    @staticmethod
    def forward(ctx, x, table, resolutions, offsets, log2_hashmap, mode, grad_into, cached):  # noqa: D102
        ext = load_extension()
        x = x.float().contiguous()  # the kernel clamps (NaN -> 0) itself
        ctx.save_for_backward(x)
        ctx.args = (table.shape[0], table.shape[1], resolutions, offsets, log2_hashmap, mode)
        ctx.grad_into = grad_into
        if cached is not None:  # computed earlier from the same x and table (no copy: autograd
            return cached  # makes the output its own tensor over the same memory)
        return ext.forward(x, table.contiguous(), resolutions, offsets, log2_hashmap)

    @staticmethod
    def backward(ctx, grad_out):  # noqa: D102
        (x,) = ctx.saved_tensors
        grad = None
        if ctx.needs_input_grad[1]:
            grad = table_backward(grad_out, x, ctx.args, ctx.grad_into)
        return None, grad, None, None, None, None, None, None


_EMPTY = torch.empty(0)


def table_backward(
    grad_out: Tensor, x: Tensor, args: tuple, leaf: torch.nn.Parameter | None
) -> Tensor | None:
    """The C++ backward of the encoding of ``x`` [N, 3] (float32, contiguous) given its gradient
    ``grad_out`` [N, L * F]: the table gradient, added into ``leaf.grad`` (None returned) or,
    without a leaf, returned. ``args``: (rows, features, resolutions, offsets, log2_hashmap,
    mode) as the kernel takes them (:meth:`HashGrid.backward_args`)."""
    ext, grad_out = load_extension(), f32(grad_out)
    if leaf is None:
        return ext.backward(grad_out, x, _EMPTY, *args)
    if leaf.grad is None:  # the kernel zeroes the new gradient level by level itself
        leaf.grad = ext.backward(grad_out, x, _EMPTY, *args)
    else:
        ext.backward(grad_out, x, leaf.grad, *args)
    return None


def hash_encode_cpp(
    x: Tensor,
    table: Tensor,
    resolutions: Sequence[int],
    offsets: Sequence[int],
    log2_hashmap: int,
    backward_mode: str = "level",
    grad_into: torch.nn.Parameter | None = None,
    cached: Tensor | None = None,
) -> Tensor:
    """The C++/OpenMP hash encoding; same arguments, result and gradient as the reference.

    Args:
        x: [N, 3] positions in the unit cube (clamped; NaN -> 0).
        table: [offsets[-1], F] float32 rows.
        resolutions, offsets, log2_hashmap: as in :func:`hash_encode_reference`.
        backward_mode: how threads share the gradient scatter: "level" (each thread owns whole
            levels; the default, race-free), "atomic" or "partial" (per-thread tables).
        grad_into: a float32 parameter (usually ``table`` itself, or the master copy ``table``
            was rounded from) whose ``.grad`` receives the table gradient added in place, with
            no full-size temporary per call ("level" mode only). Autograd then sees no gradient
            for ``table``: use with ``loss.backward()``, not ``torch.autograd.grad``.
        cached: [N, L * F] the forward result, already computed from the same ``x`` and
            ``table`` without autograd: returned (a copy) instead of computed again; the
            backward is unchanged.
    Returns:
        [N, L * F] float32, differentiable w.r.t. ``table``.
    """
    mode = BACKWARD_MODES[backward_mode]
    args = (list(resolutions), list(offsets), log2_hashmap, mode, grad_into, cached)
    return _CppEncode.apply(x, table.float(), *args)


_COMPILED = None


def _compiled_reference():
    """``torch.compile`` of :func:`hash_encode_reference` (built once per process)."""
    global _COMPILED
    if _COMPILED is None:
        _COMPILED = torch.compile(hash_encode_reference)  # dynamic N after the first recompile
    return _COMPILED
