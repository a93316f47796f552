"""Occupancy grid over the scene AABB (Instant-NGP's density grid), as config + explicit state.

The grid stores, per cell, an EMA of the optical thickness ``sigma * step`` seen at random
points in the cell; a cell is occupied while that value exceeds
``min(threshold, mean over cells)``. Updates follow Instant-NGP: every cell at every update
during warm-up, then every ``every`` steps a quarter of the cells uniformly plus a quarter
chosen among the occupied ones; the EMA keeps ``max(decay * old, new)``.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import torch
from torch import Tensor

from .draws import grid_draws, seed_from
from .grid_schedule import GridConfig, due, grid_config

# the schedule lives in grid_schedule
__all__ = ["GridConfig", "GridState", "due", "grid_config", "update"]

DensityFn = Callable[[Tensor], Tensor]  # points [N, 3] -> sigma [N]


@dataclass
class GridState:
    """density: float32 [R^3] EMA optical thickness; occupied: bool [R^3] (x-major index);
    allowed: bool [R^3] cells that may ever be occupied (the visual hull, :mod:`.carve`), or
    None (every cell)."""

    density: Tensor
    occupied: Tensor
    allowed: Tensor | None = None
    pool: Tensor | None = None  # int64 [A]: the allowed cells' indices (None: every cell)


def restrict(state: GridState, allowed: Tensor | None, pool: Tensor | None = None) -> GridState:
    """``state`` with only ``allowed`` cells (bool [R^3], None: all) ever occupied, from now on
    (``pool``: their indices when the caller has them)."""
    if allowed is None:
        return state
    allowed = allowed.to(state.occupied.device)
    pool = allowed.nonzero().squeeze(1) if pool is None else pool
    return GridState(state.density, state.occupied & allowed, allowed, pool)


def init_state(cfg: GridConfig, device: str | torch.device = "cpu") -> GridState:
    """Fresh grid: zero density, every cell occupied (nothing is skipped before training)."""
    n = cfg.res**3
    return GridState(torch.zeros(n, device=device), torch.ones(n, dtype=torch.bool, device=device))


def cell_index(points: Tensor, aabb: Tensor, res: int) -> Tensor:
    """Flat cell index [N] int64 of ``points`` [N, 3] (clamped into the grid)."""
    rel = (points - aabb[0]) / (aabb[1] - aabb[0])
    ijk = (rel * res).long().clamp_(0, res - 1)
    return (ijk[:, 0] * res + ijk[:, 1]) * res + ijk[:, 2]


def occupied_at(state: GridState, points: Tensor, aabb: Tensor) -> Tensor:
    """bool [N]: whether each point [N, 3] lies in an occupied cell (outside: clamped)."""
    res = round(state.occupied.numel() ** (1 / 3))
    return state.occupied[cell_index(points, aabb, res)]


def cell_points(cells: Tensor, res: int, aabb: Tensor, jitter: Tensor) -> Tensor:
    """The point [N, 3] at ``jitter`` [N, 3] (in [0, 1) per axis) inside each flat cell index
    of ``cells`` [N]."""
    c = cells.int()  # int32 divisions: twice as fast as int64 (res^3 < 2^31)
    ijk = torch.stack([c // (res * res), (c // res) % res, c % res], -1).float()
    return aabb[0] + (ijk + jitter) / res * (aabb[1] - aabb[0])


# A fused update (:meth:`nerf.field.Field.grid_refresh`): (density [R^3], allowed or None,
# cells [M], jitter [M, 3], aabb, res, step_size, decay, threshold) -> the new (density,
# occupied), or None where it cannot run
Refresh = Callable[..., "tuple[Tensor, Tensor] | None"]


@torch.no_grad()
def update(
    cfg: GridConfig,
    state: GridState,
    step: int,
    density_fn: DensityFn,
    aabb: Tensor,
    step_size: float,
    generator: torch.Generator,
    refresh: Refresh | None = None,
    draws=None,
) -> GridState:
    """One grid update before optimizer step ``step``; returns the new state.

    Before ``warmup`` steps every cell is sampled; later a quarter of the cells uniformly and
    a quarter drawn among the occupied ones. With ``state.allowed`` (the visual hull) only
    allowed cells are sampled, and the quarters are quarters of the allowed cells (lego: 102k
    of 262k cells, 2.6x fewer density evaluations per update): the others stay empty whatever
    the field says. Each sampled cell is evaluated at one uniformly random point in it.

    Args:
        density_fn: points [N, 3] -> sigma [N] (scene units^-1).
        aabb: [2, 3] bounds of the grid.
        step_size: marching step (scene units); optical thickness = sigma * step_size.
        refresh: the same update after the random draws in one C++ call (the field's
            :meth:`~nerf.field.Field.grid_refresh`: ~4 ms of tensor ops fewer per update on
            lego), or None.
        draws: the marching kernel (``nerf.backend.kernel("march")``), whose ``grid_draws``
            draws the cells and points (0.3 ms per lego update against ~1.4 for torch ops), or
            None (:func:`.draws.grid_draws`, the same draws by torch ops).
    """
    cells, jitter, pool = _draw(cfg, state, step, generator, draws)
    fused = None if refresh is None else refresh(
        state.density, state.allowed, cells, jitter, aabb, cfg.res, step_size, cfg.decay,
        cfg.threshold,
    )  # fmt: skip
    if fused is not None:
        return GridState(*fused, state.allowed, pool)
    fresh = torch.zeros_like(state.density)
    for start in range(0, cells.numel(), cfg.chunk):
        c, j = cells[start : start + cfg.chunk], jitter[start : start + cfg.chunk]
        sigma = density_fn(cell_points(c, cfg.res, aabb, j)).float()
        fresh.scatter_reduce_(0, c, torch.nan_to_num(sigma * step_size), "amax")
    density = torch.maximum(state.density * cfg.decay, fresh)
    thresh = min(cfg.threshold, float(density.mean()))
    return restrict(GridState(density, density > thresh), state.allowed, pool)


def _draw(
    cfg: GridConfig, state: GridState, step: int, generator: torch.Generator, ext
) -> tuple[Tensor, Tensor, Tensor | None]:
    """The cells [M] an update at ``step`` samples (:func:`update`), a uniform point in each
    (jitter [M, 3] in [0, 1)) and the allowed cells' indices (None: every cell): the draws of
    :func:`.draws.grid_draws` from one seed off ``generator``, by the kernel ``ext`` when given
    (and the grid is on the CPU), else by torch ops; the same either way."""
    pool = state.pool
    if state.allowed is not None and pool is None:  # a state built without restrict()
        pool = state.allowed.nonzero().squeeze(1)
    warm = step < cfg.warmup
    quarter = (cfg.res**3 if pool is None else pool.numel()) // 4
    seed = seed_from(generator)
    if ext is not None and state.occupied.device.type == "cpu":
        empty = torch.zeros(0, dtype=torch.int64)
        cells, jitter = ext.grid_draws(state.occupied, empty if pool is None else pool, quarter,
                                       warm, seed)  # fmt: skip
        return cells, jitter, pool
    cells, jitter = grid_draws(state.occupied, pool, quarter, warm, seed)
    dev = state.density.device
    return cells.to(dev), jitter.to(dev), pool


def to_numpy(state: GridState) -> dict:
    """The state as numpy arrays {"density": float32 [R^3], "occupied": bool [R^3]}."""
    return {"density": state.density.cpu().numpy(), "occupied": state.occupied.cpu().numpy()}


def from_numpy(g: dict, device: str | torch.device = "cpu") -> GridState:
    """Inverse of :func:`to_numpy`."""
    return GridState(
        torch.as_tensor(g["density"], dtype=torch.float32, device=device),
        torch.as_tensor(g["occupied"], dtype=torch.bool, device=device),
    )
