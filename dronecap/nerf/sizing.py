"""A model sized to the scene: each choice from the data, with the reason it was made.

The scene-sized configuration starts from the paper's MLPs and batch and sets, from the
dataset's bounds, cameras and channels:

- ``n_max`` (finest hash level): the AABB's longest side in pixel footprints, the footprint
  being ``near / focal`` (scene units per pixel at the mean near distance of the training
  views); finer levels see no detail in the images and only add hash collisions; at most
  :data:`CELLS_PER_PIXEL` per pixel of the image side (cameras inside the scene: the near
  distance is far closer than most surfaces);
- ``march_steps``: the marching step is :data:`MARCH_PER_FOOTPRINT` of a footprint, so the
  samples per ray follow the resolution instead of a fixed count (fewer samples per ray: more
  rays for the same ``batch_samples``), with the same cap;
- ``grid_res`` (occupancy grid): a cell spans about :data:`GRID_CELL_FOOTPRINTS` footprints,
  a power of two in [32, 128];
- ``log2_hashmap`` (table size T per level): the largest power of two whose modelled device
  memory stays within the budget, and no larger than the finest level needs (the AABB's
  surface in footprint squares: the occupied cells of a surface scene);
- ``channels``: the data's (1 gray, 3 RGB).

Fields the user set explicitly are kept and reported as such. The memory model is passed in
(``memory_fn``: the train command hands the GAP9 cost model's), so this module does not depend
on a device.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field

import numpy as np

from .config import TrainConfig

MARCH_PER_FOOTPRINT = 1.0  # marching step / pixel footprint
GRID_CELL_FOOTPRINTS = 4.0  # occupancy cell side / pixel footprint
CELLS_PER_PIXEL = 2  # n_max and march_steps at most this many per image pixel (longest side)
GRID_RES_RANGE = (32, 128)  # occupancy cells per axis
LOG2_T_RANGE = (12, 19)  # table sizes considered (2^12 .. 2^19 rows per level)
DEFAULT_BUDGET_MB = 21.0  # the paper's GAP9 footprint of the deployed row (Table II)

MemoryFn = Callable[[TrainConfig], float]  # configuration -> modelled device bytes


@dataclass(frozen=True)
class SceneFacts:
    """What sizing reads from a dataset (scene units, pixels).

    extent: float [3] AABB side lengths; near: mean camera-to-scene near distance of the
    training views; focal: mean focal length in pixels; width, height: image size in pixels;
    channels: C; train_images: frames trained on.
    """

    extent: tuple[float, float, float]
    near: float
    focal: float
    width: int
    height: int
    channels: int
    train_images: int

    @property
    def footprint(self) -> float:
        """Scene units covered by one pixel at the near distance."""
        return max(self.near, 1e-9) / max(self.focal, 1e-9)

    @property
    def diagonal(self) -> float:
        """AABB diagonal (scene units)."""
        return float(np.linalg.norm(self.extent))


@dataclass(frozen=True)
class Choice:
    """One sized setting: the field, the value and why (one line)."""

    field: str
    value: object
    reason: str

    def line(self) -> str:
        """``field = value: reason``."""
        return f"{self.field} = {self.value}: {self.reason}"


@dataclass
class Sizing:
    """The sized configuration and the choices that made it (in the order they were made)."""

    config: TrainConfig
    choices: list[Choice] = field(default_factory=list)
    budget_bytes: float | None = None
    memory_bytes: float | None = None

    def lines(self) -> list[str]:
        """One line per choice, as printed by ``dronecap train``."""
        return [c.line() for c in self.choices]

    def as_dict(self) -> dict:
        """JSON-able record: {"choices": [{"field", "value", "reason"}], budget/memory MB}."""
        return {
            "choices": [
                {"field": c.field, "value": c.value, "reason": c.reason} for c in self.choices
            ],
            "budget_mb": None if self.budget_bytes is None else self.budget_bytes / 1e6,
            "memory_mb": None if self.memory_bytes is None else self.memory_bytes / 1e6,
        }


def pixel_cap(facts: SceneFacts) -> int:
    """Most cells (or marching steps) across the scene the images can pin down:
    CELLS_PER_PIXEL per pixel of the longest image side. Binds when the cameras fly inside the
    scene (a corridor), where the near distance is much closer than most surfaces."""
    return CELLS_PER_PIXEL * max(facts.width, facts.height)


def finest_resolution(facts: SceneFacts) -> int:
    """Cells per axis of the finest hash level: longest AABB side / pixel footprint, within
    [16, :func:`pixel_cap`]."""
    return min(pixel_cap(facts), max(16, math.ceil(max(facts.extent) / facts.footprint)))


def march_steps(facts: SceneFacts) -> int:
    """Candidate samples along the AABB diagonal for a step of MARCH_PER_FOOTPRINT footprints,
    within [16, :func:`pixel_cap`]."""
    n = math.ceil(facts.diagonal / (MARCH_PER_FOOTPRINT * facts.footprint))
    return min(pixel_cap(facts), max(16, n))


def grid_resolution(n_max: int) -> int:
    """Occupancy cells per axis: the power of two nearest ``n_max / GRID_CELL_FOOTPRINTS``,
    clamped to GRID_RES_RANGE."""
    lo, hi = GRID_RES_RANGE
    return int(min(hi, max(lo, 2 ** round(math.log2(max(n_max / GRID_CELL_FOOTPRINTS, 1))))))


def surface_cells(facts: SceneFacts) -> float:
    """Finest-level cells a surface scene occupies: the AABB's surface in footprint squares."""
    a, b, c = (e / facts.footprint for e in facts.extent)
    return 2.0 * (a * b + b * c + a * c)


def _budgeted_table(
    config: TrainConfig, facts: SceneFacts, memory_fn: MemoryFn, budget_bytes: float
) -> tuple[int, str]:
    """log2 of the largest hash table (at most the scene's surface in footprints needs) whose
    modelled memory fits ``budget_bytes``, and the reason to print.

    Raises:
        ValueError: the smallest table considered does not fit.
    """
    need = surface_cells(facts)
    cap = min(LOG2_T_RANGE[1], max(LOG2_T_RANGE[0], math.ceil(math.log2(max(need, 1)))))
    fits = [
        t
        for t in range(LOG2_T_RANGE[0], cap + 1)
        if memory_fn(config.replace(log2_hashmap=t)) <= budget_bytes
    ]
    if not fits:
        smallest = memory_fn(config.replace(log2_hashmap=LOG2_T_RANGE[0]))
        raise ValueError(
            f"no model fits the memory budget of {budget_bytes / 1e6:.1f} MB: the "
            f"smallest table (2^{LOG2_T_RANGE[0]}) needs {smallest / 1e6:.1f} MB"
        )
    return fits[-1], (
        f"largest table within the {budget_bytes / 1e6:.3g} MB budget; the finest level "
        f"would use up to 2^{math.log2(max(need, 1)):.1f} rows (AABB surface in footprints)"
    )


def size_to_scene(
    base: TrainConfig,
    facts: SceneFacts,
    memory_fn: MemoryFn | None = None,
    budget_bytes: float | None = None,
    fixed: Iterable[str] = (),
) -> Sizing:
    """Size ``base`` to a scene (see the module docstring).

    Args:
        base: the starting configuration (its MLPs, batch, schedule are kept).
        facts: the scene, from :func:`facts_from_dataset`.
        memory_fn: configuration -> modelled device bytes; None: the table size is not
            budgeted (``base.log2_hashmap`` is kept).
        budget_bytes: device memory the model may use (with ``memory_fn``).
        fixed: fields the user set explicitly: kept as given.

    Returns:
        :class:`Sizing` (``config.auto_n_max`` is False: ``n_max`` holds the sized value).

    Raises:
        ValueError: the smallest table considered does not fit the budget.
    """
    fixed = set(fixed)
    cfg = base.replace(auto_n_max=False)
    out = Sizing(cfg, budget_bytes=budget_bytes)
    fp_mm = facts.footprint

    def choose(name: str, value: object, reason: str) -> None:
        if name in fixed:
            out.choices.append(Choice(name, getattr(out.config, name), "set by the user"))
            return
        out.config = out.config.replace(**{name: value})
        out.choices.append(Choice(name, value, reason))

    choose(
        "channels",
        facts.channels,
        f"{'gray' if facts.channels == 1 else 'RGB' if facts.channels == 3 else 'multi-channel'}"
        f" data ({facts.width}x{facts.height} px, {facts.train_images} training views)",
    )
    n_max = finest_resolution(facts)
    capped = f"; capped at {CELLS_PER_PIXEL} per image pixel ({pixel_cap(facts)})"
    choose(
        "n_max",
        n_max,
        f"longest AABB side {max(facts.extent):.3g} / pixel footprint {fp_mm:.3g} "
        f"(near {facts.near:.3g} / focal {facts.focal:.4g} px): finer levels see no detail"
        + (capped if n_max == pixel_cap(facts) else ""),
    )
    n_max = out.config.n_max
    steps = march_steps(facts)
    choose(
        "march_steps",
        steps,
        f"one sample per {MARCH_PER_FOOTPRINT:g} pixel footprint along the AABB diagonal "
        f"{facts.diagonal:.3g}" + (capped if steps == pixel_cap(facts) else ""),
    )
    choose(
        "grid_res",
        grid_resolution(n_max),
        f"occupancy cells of ~{GRID_CELL_FOOTPRINTS:g} footprints (n_max {n_max} / "
        f"{GRID_CELL_FOOTPRINTS:g}, power of two in {list(GRID_RES_RANGE)})",
    )
    if "log2_hashmap" in fixed or memory_fn is None or budget_bytes is None:
        choose("log2_hashmap", cfg.log2_hashmap, "no memory budget: the preset's table")
    else:
        choose("log2_hashmap", *_budgeted_table(out.config, facts, memory_fn, budget_bytes))
    if memory_fn is not None:
        out.memory_bytes = float(memory_fn(out.config))
    return out
