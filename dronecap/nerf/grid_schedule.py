"""When the occupancy grid is updated, and its settings: torch-free, so that the GAP9 cost model
(:mod:`dronecap.gap9.arch`) counts the trainer's own schedule without importing torch.
:mod:`.occupancy` holds the grid itself and re-exports these.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from .config import TrainConfig


@dataclass
class GridConfig:
    """Occupancy-grid settings (from TrainConfig's grid_* fields)."""

    res: int = 128  # cells per axis
    decay: float = 0.95  # EMA decay per update
    threshold: float = 0.01  # optical-thickness threshold of an occupied cell
    warmup: int = 256  # steps during which all cells are updated every step
    every: int = 16  # steps between updates after warm-up
    ramp: int = 16  # steps per unit of growth of the interval (Instant-NGP: 16)
    chunk: int = 1 << 16  # points per density evaluation


def grid_config(cfg: TrainConfig) -> GridConfig:
    """The occupancy-grid settings of a training configuration (its ``grid_*`` fields)."""
    return GridConfig(
        cfg.grid_res, cfg.grid_decay, cfg.grid_threshold, cfg.grid_warmup, cfg.grid_every,
        cfg.grid_ramp,
    )  # fmt: skip


def due(cfg: GridConfig, step: int) -> bool:
    """Whether the grid is updated before optimizer step ``step`` (0-based).

    The interval grows as ``clamp(step // ramp, 1, every)`` (Instant-NGP: ramp 16, so the
    first 32 steps update every step and the interval reaches ``every`` after ``16 * every``
    steps).
    """
    return step % min(max(step // max(cfg.ramp, 1), 1), max(cfg.every, 1)) == 0
