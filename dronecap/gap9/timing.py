"""GAP9 L3 traffic and latency of a configuration: bytes moved per tile, per Adam step and per
occupancy update, and the seconds of each kernel, step, run and rendered frame
(:func:`dronecap.gap9.model.cost_report` gathers them with memory, ops and energy).
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

from dronecap.gap9 import arch
from dronecap.gap9.arch import frame_samples, rays_per_tile
from dronecap.gap9.platform import Platform
from dronecap.nerf.config import TrainConfig

if TYPE_CHECKING:
    from dronecap.gap9.model import RunSamples


def occupancy_dma_bytes(cfg: TrainConfig, p: Platform, queries: int) -> int:
    """L3 bytes of one occupancy update: the fp32 hash params once per tile of queries, every
    cell's EMA read and written, every flag written."""
    n = p.numerics
    c = arch.counts(cfg, p.hash_rows)
    query_tiles = math.ceil(queries / cfg.tile_samples)
    grid = c.grid_cells * (2 * n.grid_density_bytes + n.grid_flag_bytes)
    return query_tiles * c.hash_params * n.param_bytes + grid


def l3_traffic(
    cfg: TrainConfig, p: Platform, spp: float, sched: arch.GridSchedule
) -> dict[str, float]:
    """L3 <-> L2 bytes per tile, per Adam step, per occupancy update (``sched``'s).

    tile: hash params read (fp32) for the forward gather + hash gradients read and written
    (fp32 accumulation) in the backward, the same for the MLP and far-field weights (the
    latter only when the model has a far field), the occupancy flags the
    rays test (``march_steps`` per ray) and the target pixels. adam: read params, gradients,
    both moments; write params and moments; zero the gradients. occupancy update: the hash
    params once per tile of queries, the grid's EMA read and written, its flags written;
    ``occupancy_run`` every update of the run's schedule. render_frame: each forward tile of a
    rendered frame reads every parameter (fp32) and its rays' occupancy flags.

    Compaction does not change a tile's bytes: the hash levels cross L3 level by level
    whatever the number of samples gathering from or scattering into them, every ray still
    tests its flags while marching and keeps its pixel.
    """
    n = p.numerics
    c = arch.counts(cfg, p.hash_rows)
    rays = rays_per_tile(cfg, spp)
    per_param_tile = n.param_bytes + 2 * n.grad_bytes
    tile = {
        "hash_params_and_grads": c.hash_params * per_param_tile,
        "mlp_params_and_grads": c.mlp_params * per_param_tile,
        "occupancy_flags": rays * cfg.march_steps * n.grid_flag_bytes,
        "pixels": rays * cfg.channels * n.image_bytes_per_pixel,
    }
    if c.far_field_params:  # the far field behind the rays (nerf.far_field), like the MLPs
        tile["far_field_params_and_grads"] = c.far_field_params * per_param_tile
    tile["total"] = sum(tile.values())
    adam = c.params * (
        n.param_bytes + 2 * n.grad_bytes + 2 * n.moment_bytes + n.param_bytes + 2 * n.moment_bytes
    )
    occupancy = occupancy_dma_bytes(cfg, p, sched.steady_queries)
    occupancy_run = sched.steady_updates * occupancy
    occupancy_run += sched.warmup_updates * occupancy_dma_bytes(cfg, p, sched.warmup_queries)
    tiles = math.ceil(cfg.batch_samples / cfg.tile_samples)
    render_tiles = math.ceil(frame_samples(cfg, spp) / cfg.tile_samples)
    forward_tile = c.params * n.param_bytes + tile["occupancy_flags"]
    return {
        "tile": tile,
        "tiles_per_step": tiles,
        "adam_step": adam,
        "step": tiles * tile["total"] + adam,
        "occupancy_update": occupancy,
        "occupancy_run": occupancy_run,
        "render_frame": render_tiles * forward_tile,
    }


def kernel_latency(
    cfg: TrainConfig, p: Platform, trained_fraction: float = 1.0
) -> dict[str, dict[str, float]]:
    """Compute seconds per tile of each kernel, forward and backward (no DMA).

    hash: corners x cycles per corner; MLPs: ops / effective ops per cycle of the pass;
    elementwise: ops / scalar FP ops per cycle; each times its share of the tile's samples
    when compaction trains on ``trained_fraction`` of them (:func:`arch.kernel_shares`).
    """
    cal, hz, tile = p.calibration, p.clock_hz, cfg.tile_samples
    per = arch.ops_per_sample(cfg)
    share = arch.kernel_shares(cfg, trained_fraction)
    out: dict[str, dict[str, float]] = {}
    for pas, rate in (
        ("forward", cal.mlp_fwd_ops_per_cycle),
        ("backward", cal.mlp_bwd_ops_per_cycle),
    ):
        ops = per[pas]
        full = {
            "hash": tile * arch.hash_corners_per_sample(cfg) * cal.hash_cycles_per_corner / hz,
            "density_mlp": tile * ops["density_mlp"] / rate / hz,
            "color_mlp": tile * ops["color_mlp"] / rate / hz,
            "elementwise": tile * ops["elementwise"] / cal.elementwise_ops_per_cycle / hz,
        }
        out[pas] = {k: share[pas][k] * v for k, v in full.items()}
    return out


def occupancy_update_s(cfg: TrainConfig, p: Platform, queries: int) -> float:
    """Seconds of one occupancy update querying ``queries`` cells (compute vs DMA, the larger)."""
    cal, hz = p.calibration, p.clock_hz
    per_query = (
        arch.hash_corners_per_sample(cfg) * cal.hash_cycles_per_corner
        + 2 * arch.mlp_macs(cfg, "density") / cal.mlp_fwd_ops_per_cycle
        + (
            arch.density_query_ops(cfg)
            - arch.hash_ops_per_sample(cfg)
            - 2 * arch.mlp_macs(cfg, "density")
        )
        / cal.elementwise_ops_per_cycle
    )
    cells = cfg.grid_res**3
    compute = (
        queries * per_query + cells * arch.GRID_CELL_OPS / cal.elementwise_ops_per_cycle
    ) / hz
    dma = occupancy_dma_bytes(cfg, p, queries) / p.l3_l2_bytes_per_s
    return max(compute, dma)


def latency(
    cfg: TrainConfig, p: Platform, spp: float, run: RunSamples, sched: arch.GridSchedule
) -> dict:
    """Per-kernel and per-step seconds (``run``'s trained share, ``sched``'s occupancy
    updates), training time for ``cfg.steps`` and the render time of a frame (forward tiles of
    every sample: rendering has no compaction)."""
    kern = kernel_latency(cfg, p, run.trained_fraction)
    traffic = l3_traffic(cfg, p, spp, sched)
    fwd, bwd = sum(kern["forward"].values()), sum(kern["backward"].values())
    dma_tile = traffic["tile"]["total"] / p.l3_l2_bytes_per_s
    tile_s = max(fwd + bwd, dma_tile)
    c = arch.counts(cfg, p.hash_rows)
    adam_ops = arch.optimizer_ops(c, p.calibration.optimizer_ops_per_value)
    adam_compute = adam_ops / p.calibration.elementwise_ops_per_cycle / p.clock_hz
    adam_dma = traffic["adam_step"] / p.l3_l2_bytes_per_s
    adam = max(adam_compute, adam_dma)
    occ_steady = occupancy_update_s(cfg, p, sched.steady_queries)
    occ_warm = occupancy_update_s(cfg, p, sched.warmup_queries)
    occ_run = sched.warmup_updates * occ_warm + sched.steady_updates * occ_steady
    tiles = traffic["tiles_per_step"]
    step = tiles * tile_s + adam + occ_run / max(cfg.steps, 1)
    render_tiles = math.ceil(frame_samples(cfg, spp) / cfg.tile_samples)
    return {
        "kernels_per_tile": kern,
        "forward_tile": fwd,
        "backward_tile": bwd,
        "l3_dma_tile": dma_tile,
        "dma_hidden": dma_tile <= fwd + bwd,
        "tile": tile_s,
        "adam_step": adam,
        "adam_bound": "L3 DMA" if adam_dma >= adam_compute else "compute",
        "occupancy_update": occ_steady,
        "occupancy_warmup_update": occ_warm,
        "occupancy_run": occ_run,
        "step": step,
        "per_tile_amortised": step / tiles,
        "train": step * cfg.steps,
        "render_tiles": render_tiles,
        "render_frame": render_tiles * sum(kernel_latency(cfg, p)["forward"].values()),
    }
