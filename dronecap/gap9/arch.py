"""What the Tiny-DroNeRF architecture holds and computes, counted from a TrainConfig.

Pure counting, no platform: parameters, the per-sample activations kept for backprop, the
occupancy-grid schedule, and the arithmetic operations of every kernel per sample. Each named
constant below is the operation count of one small piece of the algorithm, with its derivation.
"Ops" are floating-point or integer operations, a multiply-add counting 2.

Hash rows: the trainer's table stores ``T_l = min(T, (res_l + 1)^3)`` rows at level ``l`` (dense
coarse levels are smaller). The paper's figures count ``T`` rows at every level (``L * T``); that
is what reproduces Table II (see docs/gap9.md), so ``hash_rows="paper"`` is the default and
``"stored"`` counts the trainer's real rows.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from typing import Literal, get_args

from dronecap.gap9.platform import Numerics
from dronecap.nerf import levels
from dronecap.nerf.config import FAR_GRID_COLS, FAR_GRID_ROWS, FAR_SH_DEGREE, TrainConfig
from dronecap.nerf.grid_schedule import GridConfig
from dronecap.nerf.grid_schedule import due as grid_due

# --- multiresolution hash encoding, per level and per cell corner ----------------------------
HASH_LEVEL_OPS = 12  # scale x by res (3 mul), floor (3), fraction (3 sub), 1 - fraction (3 sub)
HASH_INDEX_OPS = 6  # spatial hash of a corner: 3 mul by the primes, 2 xor, 1 mask (mod T = 2^k)
HASH_WEIGHT_OPS = 2  # trilinear weight of a corner: product of its three 1-D weights
CORNERS = 8  # corners of a 3-D cell
# forward blend: F multiply-adds per corner (2F ops); backward: F multiplies w*g + F scatter-adds
# --- direction encoding, activations, rendering, loss ----------------------------------------
SH_OPS_PER_COEFF = 3  # each real SH basis function: ~3 mul/add of the previous bands' terms
RELU_OPS = 1  # forward: max(0, x); backward: mask the gradient
DENSITY_ACT_OPS = 1  # exp of the raw density (forward), times its value (backward)
SIGMOID_FWD_OPS = 4  # neg, exp, add 1, divide
SIGMOID_BWD_OPS = 2  # s * (1 - s) * g
RENDER_FWD_BASE_OPS = 6  # alpha = 1 - exp(-sigma dt) (3), w = T alpha (1), T *= 1 - alpha (2)
# ... plus 2 per colour channel (accumulate w * c); the backward costs twice the forward.
HUBER_FWD_OPS = 4  # per ray and channel: difference, abs, compare, quadratic/linear branch
HUBER_BWD_OPS = 2  # per ray and channel: clamp of the difference, scale
# --- optimizer and occupancy grid ------------------------------------------------------------
ADAM_OPS = 14  # m (3), v (4), two bias corrections (2), sqrt (1), + eps (1), divide (1), step (2)
# The per-value work of an optimizer step that Table II counts is larger than Adam's arithmetic
# (its compute grows ~45 ops per trainable value, fitted: Calibration.optimizer_ops_per_value);
# ADAM_OPS is the lower bound that fit must exceed.
WEIGHT_DECAY_OPS = 2  # L2 on MLP weights: g += wd * w
EMA_OPS = 3  # per queried cell: decay * old, max with the new density, compare with threshold
GRID_CELL_OPS = 2  # per cell and update: sum for the mean density, re-derive the occupied flag


def level_resolutions(cfg: TrainConfig) -> list[int]:
    """Cells per axis of each level, by the trainer's own formula
    (:func:`dronecap.nerf.levels.level_resolutions`) at ``cfg.n_max`` (the resolved value)."""
    return levels.level_resolutions(cfg.levels, cfg.n_min, cfg.n_max)


def hash_rows_per_level(cfg: TrainConfig, mode: str = "paper") -> list[int]:
    """Rows of each level: ``T`` (mode "paper") or ``min(T, (res_l + 1)^3)`` (mode "stored")."""
    t = 1 << cfg.log2_hashmap
    if mode == "paper":
        return [t] * cfg.levels
    return [min(t, (res + 1) ** 3) for res in level_resolutions(cfg)]


def mlp_layers(cfg: TrainConfig) -> dict[str, list[tuple[int, int]]]:
    """(inputs, outputs) of each bias-free linear layer of the density and colour MLPs."""

    def chain(n_in: int, layers: int, n_out: int) -> list[tuple[int, int]]:
        widths = [n_in] + [cfg.hidden] * layers + [n_out]
        return list(zip(widths[:-1], widths[1:], strict=True))

    color_in = cfg.geo_features + cfg.sh_degree**2
    return {
        "density": chain(cfg.levels * cfg.features, cfg.density_layers, cfg.geo_features),
        "color": chain(color_in, cfg.color_layers, cfg.channels),
    }


@dataclass(frozen=True)
class Counts:
    """Sizes of the model for one configuration."""

    hash_rows: int  # rows over all levels, in the chosen counting mode
    hash_rows_paper: int  # L * T
    hash_rows_stored: int  # sum of min(T, (res_l + 1)^3)
    hash_params: int  # hash_rows * F
    density_mlp_params: int
    color_mlp_params: int
    grid_cells: int  # grid_res^3
    far_field_params: int = 0  # the far field's values (nerf.far_field; 0 without one)

    @property
    def mlp_params(self) -> int:
        """Weights of both MLPs."""
        return self.density_mlp_params + self.color_mlp_params

    @property
    def params(self) -> int:
        """All trainable values."""
        return self.hash_params + self.mlp_params + self.far_field_params


def counts(cfg: TrainConfig, hash_rows: str = "paper") -> Counts:
    """Parameter and grid sizes; e.g. tiny-dronerf: 16 x 8192 rows x 2 = 262144 hash params,
    3072 density + 6336 colour MLP weights, 128^3 = 2097152 grid cells."""
    layers = mlp_layers(cfg)
    rows = sum(hash_rows_per_level(cfg, hash_rows))
    return Counts(
        hash_rows=rows,
        hash_rows_paper=sum(hash_rows_per_level(cfg, "paper")),
        hash_rows_stored=sum(hash_rows_per_level(cfg, "stored")),
        hash_params=rows * cfg.features,
        density_mlp_params=sum(a * b for a, b in layers["density"]),
        color_mlp_params=sum(a * b for a, b in layers["color"]),
        grid_cells=cfg.grid_res**3,
        far_field_params=far_field_params(cfg.far_field, cfg.channels),
    )


def far_field_params(kind: str, channels: int) -> int:
    """Learned values of a far field (:mod:`dronecap.nerf.far_field`) of ``kind`` with
    ``channels`` channels: 16 C for "sh", 16 x 32 C for "grid", 0 for "none" and for an
    unresolved "auto" (as the trainer's Field builds it)."""
    per_channel = {"sh": FAR_SH_DEGREE**2, "grid": FAR_GRID_ROWS * FAR_GRID_COLS}
    return per_channel.get(kind, 0) * channels


def far_field_ops_per_ray(kind: str, channels: int) -> int:
    """Forward + backward ops of one ray's far-field colour and its compositing
    ``T_exit * far(d)``, a multiply-add 2 ops and a sigmoid 4.

    sh: the 16 basis values (~30 ops), a 16-term dot product (32), the sigmoid (4) and
    compositing (2) per channel; backward a 16-term gradient scatter (32) and 6 per channel.
    grid: the direction to map coordinates (atan2 + asin, ~40 ops), 4 taps and 3 lerps (10),
    sigmoid (4) and compositing (2) per channel; backward 4 weighted scatters (8) and 6.
    """
    n = FAR_SH_DEGREE**2
    if kind == "sh":
        return 30 + channels * (2 * n + 4 + 2) + channels * (2 * n + 6)
    if kind == "grid":
        return 40 + channels * (10 + 4 + 2) + channels * (8 + 6)
    return 0


# ---------------------------------------------------------------------------------------------
# activations kept for backprop, per sample
# ---------------------------------------------------------------------------------------------


def activation_values(cfg: TrainConfig) -> dict[str, int]:
    """Values each sample's forward pass keeps for the backward pass (one blob per layer output).

    encoding: L*F hash features (density-MLP input); density_hidden / color_hidden: hidden
    layers after ReLU; density_out: geo_features (raw density first); sh: sh_degree^2 direction
    coefficients; color_in: concatenated geo + SH (colour-MLP input); color_out: C channels.
    """
    return {
        "encoding": cfg.levels * cfg.features,
        "density_hidden": cfg.density_layers * cfg.hidden,
        "density_out": cfg.geo_features,
        "sh": cfg.sh_degree**2,
        "color_in": cfg.geo_features + cfg.sh_degree**2,
        "color_hidden": cfg.color_layers * cfg.hidden,
        "color_out": cfg.channels,
    }


def boundary_gradient_values(cfg: TrainConfig) -> dict[str, int]:
    """Per-sample gradient buffers between fused kernels (a fully fused MLP keeps its hidden
    layers' gradients on chip): d/d encoding, d/d density output, d/d colour input, and the
    rendering's d/d (colour, density)."""
    return {
        "encoding": cfg.levels * cfg.features,
        "density_out": cfg.geo_features,
        "color_in": cfg.geo_features + cfg.sh_degree**2,
        "render": cfg.channels + 1,
    }


def all_gradient_values(cfg: TrainConfig) -> dict[str, int]:
    """Per-sample gradient ('diff') buffer of every differentiated layer output, as a
    layer-at-a-time embedded implementation allocates them (the SH input has none)."""
    return {k: v for k, v in activation_values(cfg).items() if k != "sh"}


def sample_record_bytes(num: Numerics) -> int:
    """Per-sample position kept to recompute hash indices and weights in the backward (3 coords).

    The direction lives on in the SH blob; the marching step dt is one constant per grid."""
    return 3 * num.coord_bytes


def act_bytes_per_sample(cfg: TrainConfig, num: Numerics) -> int:
    """Bytes per sample of the whole-batch (untiled) training step, Table II's accounting:
    forward blobs + boundary gradients + the sample position. tiny-dronerf: 291 + 84 values
    of fp16 + 12 B = 762 B."""
    values = sum(activation_values(cfg).values()) + sum(boundary_gradient_values(cfg).values())
    return values * num.act_bytes + sample_record_bytes(num)


def tile_bytes_per_sample(cfg: TrainConfig, num: Numerics) -> int:
    """Bytes per sample of a GAP9 tile in L2: forward blobs + every layer's gradient buffer +
    the sample position. tiny-dronerf: (291 + 275) fp16 + 12 B = 1144 B."""
    values = sum(activation_values(cfg).values()) + sum(all_gradient_values(cfg).values())
    return values * num.act_bytes + sample_record_bytes(num)


# ---------------------------------------------------------------------------------------------
# operations
# ---------------------------------------------------------------------------------------------


def hash_corners_per_sample(cfg: TrainConfig) -> int:
    """Table rows touched per sample: 8 corners at each of the L levels (forward or backward)."""
    return CORNERS * cfg.levels


def hash_ops_per_sample(cfg: TrainConfig) -> int:
    """Ops of the hash encoding per sample, forward (the backward recomputes index and weight
    and spends F multiplies + F scatter-adds per corner: the same count).
    tiny-dronerf: 16 x (12 + 8 x (6 + 2 + 4)) = 1728."""
    per_corner = HASH_INDEX_OPS + HASH_WEIGHT_OPS + 2 * cfg.features
    return cfg.levels * (HASH_LEVEL_OPS + CORNERS * per_corner)


def mlp_macs(cfg: TrainConfig, which: str) -> int:
    """Multiply-accumulates per sample of one MLP's forward ("density" or "color")."""
    return sum(a * b for a, b in mlp_layers(cfg)[which])


def elementwise_ops_per_sample(cfg: TrainConfig) -> dict[str, int]:
    """Scalar ops per sample outside the matmuls and the hash grid: activations, SH, rendering.

    forward: ReLU on every hidden unit, exp of the density, sigmoid of the colour, SH encoding,
    volume-rendering accumulation; backward: the same activations' derivatives and twice the
    rendering (the SH input needs no gradient). tiny-dronerf: 265 forward, 223 backward.
    """
    hidden_units = cfg.hidden * (cfg.density_layers + cfg.color_layers)
    render_fwd = RENDER_FWD_BASE_OPS + 2 * cfg.channels
    fwd = (
        RELU_OPS * hidden_units
        + DENSITY_ACT_OPS
        + SIGMOID_FWD_OPS * cfg.channels
        + SH_OPS_PER_COEFF * cfg.sh_degree**2
        + render_fwd
    )
    bwd = (
        RELU_OPS * hidden_units + DENSITY_ACT_OPS + SIGMOID_BWD_OPS * cfg.channels + 2 * render_fwd
    )
    return {"forward": fwd, "backward": bwd}


def ops_per_sample(cfg: TrainConfig) -> dict[str, dict[str, int]]:
    """Ops per training sample by pass and kernel: hash, density_mlp, color_mlp, elementwise.

    Forward matmul = 2 ops per MAC; backward = 4 (input gradient + weight gradient; generic
    linear-backward kernels compute the whole input gradient). tiny-dronerf: 20809 forward,
    39583 backward.
    """
    ew = elementwise_ops_per_sample(cfg)
    dens, col = mlp_macs(cfg, "density"), mlp_macs(cfg, "color")
    hashed = hash_ops_per_sample(cfg)
    return {
        "forward": {
            "hash": hashed,
            "density_mlp": 2 * dens,
            "color_mlp": 2 * col,
            "elementwise": ew["forward"],
        },
        "backward": {
            "hash": hashed,
            "density_mlp": 4 * dens,
            "color_mlp": 4 * col,
            "elementwise": ew["backward"],
        },
    }


def prepass_ops_per_sample(cfg: TrainConfig) -> dict[str, int]:
    """Forward ops per marched sample of compaction's pre-pass (:mod:`dronecap.nerf.compaction`):
    the hash encoding, the density MLP with its ReLUs and exp, and the transmittance scan
    (alpha and T of the rendering forward) that finds the samples behind an opaque surface.

    A GAP9 tile keeps these forward blobs in L2 whatever the pass, so its training pass on the
    kept samples reuses them and spends the rest of :func:`ops_per_sample` (the CPU trainer,
    under autograd, runs the density MLP forward again). tiny-dronerf: 1728 + 6144 + 71.
    """
    return {
        "hash": hash_ops_per_sample(cfg),
        "density_mlp": 2 * mlp_macs(cfg, "density"),
        "elementwise": RELU_OPS * cfg.hidden * cfg.density_layers + DENSITY_ACT_OPS
        + RENDER_FWD_BASE_OPS,
    }  # fmt: skip


def kernel_shares(cfg: TrainConfig, trained_fraction: float) -> dict[str, dict[str, float]]:
    """Share of a batch's ops (:func:`ops_per_sample` x ``batch_samples``) each kernel spends
    when compaction trains on ``trained_fraction`` of the marched samples, by pass and kernel:
    the pre-pass part of a forward kernel runs on every marched sample, the rest of it and every
    backward kernel on the trained ones. The batch counts the trained samples when
    ``cfg.batch_counts`` is "trained" (a step marches B / trained_fraction samples), the marched
    ones otherwise. 1.0 everywhere at ``trained_fraction`` 1 (no compaction)."""
    per, pre = ops_per_sample(cfg), prepass_ops_per_sample(cfg)
    f = trained_fraction
    marched = 1 / f if cfg.batch_counts == "trained" else 1.0  # per sample of the batch
    return {
        "forward": {k: (marched * pre.get(k, 0) + marched * f * (v - pre.get(k, 0))) / v
                    for k, v in per["forward"].items()},
        "backward": dict.fromkeys(per["backward"], marched * f),
    }  # fmt: skip


def loss_ops_per_ray(cfg: TrainConfig) -> int:
    """Huber loss forward + backward per ray (per channel), and the far field's colour behind
    the ray when the model has one (:func:`far_field_ops_per_ray`)."""
    far = far_field_ops_per_ray(cfg.far_field, cfg.channels)
    return (HUBER_FWD_OPS + HUBER_BWD_OPS) * cfg.channels + far


def optimizer_ops(c: Counts, ops_per_value: float) -> float:
    """Ops of one optimizer step: ``ops_per_value`` on every trainable value (at least Adam's
    :data:`ADAM_OPS`; the cost model passes the platform's fitted
    ``Calibration.optimizer_ops_per_value``) plus weight decay on the MLP weights."""
    return ops_per_value * c.params + WEIGHT_DECAY_OPS * c.mlp_params


def density_query_ops(cfg: TrainConfig) -> int:
    """Ops of one occupancy-grid query: hash encoding + density MLP forward + ReLU + exp + EMA.
    tiny-dronerf: 1728 + 6144 + 64 + 1 + 3 = 7940."""
    relu = RELU_OPS * cfg.hidden * cfg.density_layers
    return (
        hash_ops_per_sample(cfg) + 2 * mlp_macs(cfg, "density") + relu + DENSITY_ACT_OPS + EMA_OPS
    )


GridRule = Literal["trainer", "fixed"]
"""When the occupancy grid is updated: "trainer" is the trainer's own rule
(:func:`dronecap.nerf.grid_schedule.due`: the interval grows as
``clamp(step // grid_ramp, 1, grid_every)``, Instant-NGP's with ramp 16); "fixed" is the
paper's GAP9 run as it states it, every step for ``grid_warmup`` steps, then every
``grid_every`` steps."""
GRID_RULES: tuple[GridRule, ...] = get_args(GridRule)
DEFAULT_GRID_RULE: GridRule = "trainer"  # a run on GAP9 updates its grid as the trainer did


@dataclass(frozen=True)
class GridSchedule:
    """Occupancy-grid updates over a run of ``cfg.steps`` steps."""

    warmup_updates: int  # updates before step grid_warmup: every cell of the hull
    steady_updates: int  # later updates
    warmup_queries: int  # cells queried by one warm-up update (the hull's cells)
    steady_queries: int  # cells queried by a later update (1/4 uniform + 1/4 occupied of the hull)

    @property
    def total_queries(self) -> int:
        """Density queries over the whole run."""
        return self.warmup_updates * self.warmup_queries + self.steady_updates * self.steady_queries

    @property
    def updates(self) -> int:
        """Updates over the whole run."""
        return self.warmup_updates + self.steady_updates


@functools.lru_cache(maxsize=256)
def grid_updates(
    steps: int, warmup: int, every: int, ramp: int, rule: GridRule = DEFAULT_GRID_RULE
) -> tuple[int, int]:
    """(updates before step ``warmup``, updates from it on) over ``steps`` optimizer steps.

    "trainer" counts the steps :func:`dronecap.nerf.grid_schedule.due` says are due (the rule
    lives there only; ``ramp`` is its interval growth; 10k steps, warm-up 256, every 16, ramp
    16: 76 + 609); "fixed" counts ``min(steps, warmup)`` warm-up updates and ``(steps -
    warmup) // every`` later ones (10k steps, no warm-up, every 256: 0 + 39).
    """
    if rule == "fixed":
        warm = min(steps, warmup)
        return warm, (steps - warm) // every
    grid = GridConfig(warmup=warmup, every=every, ramp=ramp)
    due = [s for s in range(steps) if grid_due(grid, s)]
    warm = sum(1 for s in due if s < warmup)
    return warm, len(due) - warm


def grid_schedule(
    cfg: TrainConfig, hull_fraction: float = 1.0, rule: GridRule = DEFAULT_GRID_RULE
) -> GridSchedule:
    """The occupancy updates of ``cfg.steps`` steps by ``rule`` (:func:`grid_updates`): warm-up
    updates query every cell of the visual hull (``hull_fraction`` of the ``grid_res^3``
    cells; 1.0 without one), later ones a quarter of the hull uniformly plus as many occupied
    cells (:func:`dronecap.nerf.occupancy.update`). Instant-NGP's 35k steps, warm-up 256,
    every 16, 128^3 cells, no hull: 76 + 2172 updates, 2.44e9 queries (69.6k per step)."""
    hull = round(hull_fraction * cfg.grid_res**3)
    warm, steady = grid_updates(cfg.steps, cfg.grid_warmup, cfg.grid_every, cfg.grid_ramp, rule)
    return GridSchedule(warm, steady, hull, 2 * (hull // 4))


def rays_per_tile(cfg: TrainConfig, spp: float) -> float:
    """Rays whose samples fill one tile, at ``spp`` samples per ray on average."""
    return cfg.tile_samples / spp


def frame_samples(cfg: TrainConfig, spp: float) -> float:
    """Samples of one rendered ``resolution^2`` frame at ``spp`` samples per pixel."""
    return cfg.resolution**2 * spp
