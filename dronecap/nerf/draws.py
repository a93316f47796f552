"""A training step's random numbers from one seed: splitmix64 streams, in torch as in C++.

A step's pixels (:func:`pixel_draws`) and an occupancy update's cells and points
(:func:`grid_draws`) come from a splitmix64 stream seeded by one number off the trainer's
generator: number ``i`` of stream ``seed`` is splitmix64 of ``seed + (i + 1) * golden``, so a
draw does not depend on which thread makes it. The marching kernel (``csrc/march.cpp``:
``draw_random``, ``grid_draws``) draws them in one call; the functions here are the same draws
in torch's int64 ops, bit for bit (tests/nerf/test_frame_cameras.py, test_marching.py), for
where the kernel does not run. One ``torch.randint`` for the seed replaces ~6 random tensor
ops per step (each ~10 us between the kernels) and mt19937's ~2.4 ns per number.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

# splitmix64's constants as int64 (torch has no uint64 arithmetic; the bits are the same)
_GOLDEN, _MIX1, _MIX2 = (c - (1 << 64) for c in (0x9E3779B97F4A7C15, 0xBF58476D1CE4E5B9,
                                                 0x94D049BB133111EB))  # fmt: skip


def seed_from(generator: torch.Generator) -> int:
    """One stream's seed (in [0, 2^62)) off ``generator``."""
    return int(torch.randint(2**62, (1,), generator=generator, device=generator.device))


def pixel_draws(
    seed: int, n_img: int, k: int, n_rays: int, shape: tuple[int, int, int], random_bg: bool
) -> tuple[Tensor, Tensor, Tensor, Tensor | None]:
    """The random pixels of a step (``nerf.batch.draw_rays``), as the kernel's ``draw_random``
    draws them: ``k`` frames uniformly among ``n_img`` (numbers 0 .. k-1), then per ray ``p`` a
    frame uniformly among those, a column and a row (numbers k + 3p + 0, 1, 2; ``shape`` = (H,
    W, C)), and with ``random_bg`` a uniform background colour (numbers k + 3R + pC + ch; else
    None).

    Returns:
        frame, column, row int64 [R]; background float32 [R, C] or None (CPU tensors).
    """
    h, w, c = shape
    frames = _below32(_mix(seed, torch.arange(k)), n_img)
    i = k + 3 * torch.arange(n_rays)
    which = frames[_below32(_mix(seed, i), k)]
    u, v = _below32(_mix(seed, i + 1), w), _below32(_mix(seed, i + 2), h)
    bg = None
    if random_bg:
        r = _mix(seed, k + 3 * n_rays + torch.arange(n_rays * c))
        bg = (_shifted(r, 40).float() * 2.0**-24).reshape(n_rays, c)
    return which, u, v, bg


def grid_draws(
    occupied: Tensor, pool: Tensor | None, quarter: int, warm: bool, seed: int
) -> tuple[Tensor, Tensor]:
    """The cells an occupancy update samples and a uniform point in each, as the kernel's
    ``grid_draws`` draws them: in warm-up every cell of ``pool`` (the allowed cells; None: every
    cell of the bool [N] grid ``occupied``); after it ``quarter`` cells uniformly from the pool
    or grid (numbers 0 .. quarter-1) and ``quarter`` uniformly from the occupied cells (numbers
    quarter .. 2 quarter - 1; none when no cell is). The points: two 24-bit uniforms from each
    number of the stream seeded by number -1 (2^64 - 1).

    Returns:
        cells int64 [M]; jitter float32 [M, 3] in [0, 1) (CPU tensors).
    """
    n = occupied.numel()
    if warm:
        cells = torch.arange(n) if pool is None else pool.cpu().clone()
    else:
        i = torch.arange(quarter)
        span = n if pool is None else pool.numel()
        u = _below32(_mix(seed, i), max(span, 1))
        cells = u if pool is None else pool.cpu()[u]
        occ = torch.from_numpy(np.flatnonzero(occupied.cpu().numpy()))
        if occ.numel():
            cells = torch.cat([cells, occ[_below32(_mix(seed, quarter + i), occ.numel())]])
    m = cells.numel()
    stream = int(_mix(seed, torch.tensor([-1]))[0])
    r = _mix(stream, torch.arange((3 * m + 1) // 2))
    pairs = torch.stack([_shifted(r, 40), (r & 0xFFFFFFFF) >> 8], 1).float() * 2.0**-24
    return cells, pairs.reshape(-1)[: 3 * m].reshape(m, 3)


def _mix(seed: int, index: Tensor) -> Tensor:
    """splitmix64 of numbers ``index`` (int64) of stream ``seed``, in int64 bits."""
    z = (index + 1) * _GOLDEN + seed
    z = (z ^ _shifted(z, 30)) * _MIX1
    z = (z ^ _shifted(z, 27)) * _MIX2
    return z ^ _shifted(z, 31)


def _shifted(z: Tensor, bits: int) -> Tensor:
    """The logical right shift of int64 bits (torch's ``>>`` is arithmetic)."""
    return (z >> bits) & ((1 << (64 - bits)) - 1)


def _below32(r: Tensor, k: int) -> Tensor:
    """Uniform in [0, k) from the high 32 bits of ``r`` (k < 2^31)."""
    return (_shifted(r, 32) * k) >> 32
