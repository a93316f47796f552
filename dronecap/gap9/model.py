"""GAP9 cost model: memory, operations, latency, L3 traffic, energy and radio time of a training
configuration, as the paper's embedded implementation would spend them.

The implementation modelled (the paper's Deployment section):

- every trainable value lives in L3 as fp32 master + fp32 gradient + two fp32 Adam moments;
  arithmetic is fp16 SIMD; a step of ``B`` samples is processed as ``ceil(B / tile)`` tiles of
  ``tile_samples`` with gradients accumulated, then one Adam update;
- a tile's activations and their gradient buffers stay in L2; hash levels come L3 -> L2 one at a
  time (double-buffered) for the gather (forward) and the gradient read-modify-write (backward);
  MLP kernels stream sub-tiles L2 -> L1 sized to fill L1;
- DMA overlaps computation: a kernel takes max(compute, transfer);
- the occupancy grid (fp32 EMA + a byte flag per cell) is updated on its own schedule.

Public API: :func:`cost_report`, :func:`format_report`, :func:`federated_payload` and
:func:`link_time_s` (from :mod:`.link`), :class:`Platform`, :func:`load_platform`. All sizes in
bytes, times in seconds, energies in joules, ops as counted in :mod:`dronecap.gap9.arch`.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

from dronecap.gap9 import arch
from dronecap.gap9.arch import frame_samples
from dronecap.gap9.energy import energy_report
from dronecap.gap9.link import federated_payload, link_report, link_time_s
from dronecap.gap9.platform import Platform, load_platform
from dronecap.gap9.report_format import format_report
from dronecap.gap9.timing import l3_traffic, latency
from dronecap.nerf.config import TrainConfig

__all__ = [
    "Platform",
    "RunSamples",
    "cost_report",
    "federated_payload",
    "format_report",
    "link_time_s",
    "load_platform",
]


def _platform(platform: Platform | None) -> Platform:
    return platform if platform is not None else load_platform()


@dataclass(frozen=True)
class RunSamples:
    """What a trained run's steps worked on, as its ``metrics.json`` "samples" records them
    (:meth:`dronecap.nerf.trainer.Trainer.sample_counts`), averaged over the run.

    trained_fraction: samples trained on after compaction / samples marched (1.0: no
    compaction); hull_fraction: share of the occupancy cells the visual hull allows (1.0: no
    carved grid). The defaults cost a run as if neither existed.
    """

    trained_fraction: float = 1.0
    hull_fraction: float = 1.0

    def __post_init__(self) -> None:
        for name in ("trained_fraction", "hull_fraction"):
            value = getattr(self, name)
            if not 0 < value <= 1:
                raise ValueError(f"{name} must be in (0, 1], got {value}")

    @classmethod
    def from_metrics(cls, doc: dict) -> RunSamples:
        """The fractions of a run's ``metrics.json`` document; a run written before they were
        recorded (no "samples") gets the defaults: every marched sample trained, no hull."""
        s = doc.get("samples")
        if not s:
            return cls()
        marched = int(s["marched"])
        return cls(int(s["trained"]) / marched if marched else 1.0, float(s["hull_fraction"]))


# ---------------------------------------------------------------------------------------------
# memory
# ---------------------------------------------------------------------------------------------


def param_state_bytes(c: arch.Counts, p: Platform) -> dict[str, int]:
    """Parameters, gradients and Adam moments of every trainable value (hash + MLPs), bytes."""
    n = p.numerics
    return {
        "parameters": c.params * n.param_bytes,
        "gradients": c.params * n.grad_bytes,
        "optimizer_state": c.params * 2 * n.moment_bytes,
    }


def grid_bytes(c: arch.Counts, p: Platform) -> int:
    """Occupancy grid: fp32 EMA density + one flag byte per cell (128^3 -> 10.49 MB)."""
    return c.grid_cells * (p.numerics.grid_density_bytes + p.numerics.grid_flag_bytes)


def image_bytes(cfg: TrainConfig, p: Platform, n_images: int) -> int:
    """``n_images`` stored images of ``resolution^2`` pixels at 1 byte/pixel (100 x 160^2 =
    2.56 MB, the paper's accounting)."""
    return n_images * cfg.resolution**2 * p.numerics.image_bytes_per_pixel


def total_memory(cfg: TrainConfig, p: Platform) -> dict[str, int]:
    """Whole footprint of one training step with no tiling (Table II's Mem): parameter state,
    activations of all ``B`` samples, occupancy grid, and the images of one step."""
    c = arch.counts(cfg, p.hash_rows)
    out = dict(param_state_bytes(c, p))
    out["activations"] = cfg.batch_samples * arch.act_bytes_per_sample(cfg, p.numerics)
    out["occupancy_grid"] = grid_bytes(c, p)
    out["images"] = image_bytes(cfg, p, cfg.images_per_step)
    out["total"] = sum(out.values())
    return out


def l2_phases(cfg: TrainConfig, p: Platform, spp: float, tile: int | None = None) -> dict[str, int]:
    """L2 bytes in each phase of a tile: the tile's blobs (always) + what the phase adds.

    resident: ``tile`` x (forward blobs + gradient buffers + position) and the rays of the tile
    (origin, direction, accumulated colour and transmittance, target pixel);
    hash_level: + ``level_buffers`` fp32 slices of one level (params forward, gradients backward);
    density_mlp / color_mlp: + that MLP's fp32 weights and gradients.
    """
    n = p.numerics
    tile = cfg.tile_samples if tile is None else tile
    c = arch.counts(cfg, p.hash_rows)
    rays = math.ceil(tile / spp)
    ray_bytes = 6 * n.coord_bytes + (cfg.channels + 1) * 4 + cfg.channels * n.image_bytes_per_pixel
    resident = tile * arch.tile_bytes_per_sample(cfg, n) + rays * ray_bytes
    level_rows = max(arch.hash_rows_per_level(cfg, p.hash_rows))
    level = p.level_buffers * level_rows * cfg.features * max(n.param_bytes, n.grad_bytes)
    mlp_state = n.param_bytes + n.grad_bytes
    return {
        "resident": resident,
        "hash_level": resident + level,
        "density_mlp": resident + c.density_mlp_params * mlp_state,
        "color_mlp": resident + c.color_mlp_params * mlp_state,
    }


def l1_peak(cfg: TrainConfig, p: Platform) -> dict[str, int | str]:
    """L1 working set of the MLP-layer backward kernels, all run with one sub-tile size.

    Per layer (n_in, n_out): fp16 weights + fp32 weight-gradient accumulator, and per sample
    the input blob, its gradient, the output blob (ReLU mask) and its gradient in fp16, twice
    (double-buffered DMA). The sub-tile is the largest multiple of the worker cores with which
    every layer fits ``l1_bytes - l1_reserved_bytes`` (at least one sample per core); the peak is
    the layer that needs most with it (tiny-dronerf: colour hidden 64x64, 80 samples, 106.5 kB).
    """
    n = p.numerics
    budget = p.l1_bytes - p.l1_reserved_bytes
    layers = [
        (
            f"{which}[{i}] {a}x{b}",
            a * b * (n.act_bytes + n.grad_bytes),
            2 * 2 * (a + b) * n.act_bytes,
        )
        for which, chain in arch.mlp_layers(cfg).items()
        for i, (a, b) in enumerate(chain)
    ]
    fit = min(max(0, budget - fixed) // per_sample for _, fixed, per_sample in layers)
    sub = max(p.worker_cores, fit - fit % p.worker_cores)
    name, fixed, per_sample = max(layers, key=lambda x: x[1] + sub * x[2])
    return {"bytes": fixed + sub * per_sample, "layer": name, "subtile": sub}


def largest_tile_in_l2(cfg: TrainConfig, p: Platform, spp: float) -> int:
    """Largest power-of-two tile whose L2 peak fits ``l2_bytes`` (0 if not even 1 sample)."""
    tile = 1
    if max(l2_phases(cfg, p, spp, 1).values()) > p.l2_bytes:
        return 0
    while max(l2_phases(cfg, p, spp, tile * 2).values()) <= p.l2_bytes and tile < 1 << 24:
        tile *= 2
    return tile


def l3_resident(cfg: TrainConfig, p: Platform, n_images: int) -> dict[str, int]:
    """What the tiled GAP9 implementation keeps in L3: parameter state, grid, stored images."""
    c = arch.counts(cfg, p.hash_rows)
    out = {"parameter_state": sum(param_state_bytes(c, p).values())}
    out["occupancy_grid"] = grid_bytes(c, p)
    out["images"] = image_bytes(cfg, p, n_images)
    out["total"] = sum(out.values())
    return out


# ---------------------------------------------------------------------------------------------
# operations
# ---------------------------------------------------------------------------------------------


def step_ops(
    cfg: TrainConfig, p: Platform, spp: float, run: RunSamples, sched: arch.GridSchedule
) -> dict[str, float]:
    """Ops of one optimizer step (Table II's Compute): forward and backward of ``B`` marched
    samples (with compaction: the pre-pass on all of them, the rest on ``run``'s trained
    share, :func:`arch.kernel_shares`), loss per ray, Adam, and the occupancy updates of
    ``sched`` amortised over the run's steps."""
    per = arch.ops_per_sample(cfg)
    share = arch.kernel_shares(cfg, run.trained_fraction)
    c = arch.counts(cfg, p.hash_rows)
    occ_total = sched.total_queries * arch.density_query_ops(cfg)
    occ_total += sched.updates * c.grid_cells * arch.GRID_CELL_OPS
    out = {
        pas: cfg.batch_samples * sum(share[pas][k] * v for k, v in per[pas].items())
        for pas in ("forward", "backward")
    } | {
        "loss": cfg.batch_samples / spp * arch.loss_ops_per_ray(cfg),
        "optimizer": arch.optimizer_ops(c, p.calibration.optimizer_ops_per_value),
        "occupancy_amortised": occ_total / max(cfg.steps, 1),
    }
    out["total"] = sum(out.values())
    return out


# ---------------------------------------------------------------------------------------------
# the report
# ---------------------------------------------------------------------------------------------

_CONFIG_FIELDS = (
    "images_per_step", "resolution", "batch_samples", "tile_samples", "levels", "features",
    "log2_hashmap", "n_min", "n_max", "hidden", "density_layers", "color_layers", "geo_features",
    "sh_degree", "channels", "grid_res", "grid_warmup", "grid_every", "grid_ramp", "march_steps",
    "steps", "train_images", "precision", "far_field",
)  # fmt: skip


DEPLOY_TILE = 1024  # samples per tile on GAP9 (the paper's deployment; fits its 1.5 MB L2)


def deployed(cfg: TrainConfig) -> TrainConfig:
    """The configuration a trained run would run on GAP9: the same model and batch in tiles of
    at most :data:`DEPLOY_TILE` samples. On the CPU a run may accumulate fewer, larger tiles
    (faster there); tiles only split the batch, so the trained model is the same."""
    return cfg.replace(tile_samples=min(cfg.tile_samples, DEPLOY_TILE))


def memory_bytes(cfg: TrainConfig) -> float:
    """Modelled GAP9 memory of ``cfg`` in bytes (Table II accounting, untiled): what a sized
    configuration's table must fit in (the ``memory_fn`` ``dronecap train`` gives
    :func:`dronecap.nerf.resolve.resolve`)."""
    return cost_report(cfg)["memory"]["untiled"]["total"]


def _counts(cfg: TrainConfig, p: Platform, c: arch.Counts, per: dict) -> dict:
    """The report's "counts": parameters by kind, bytes per sample, ops per sample (``per``)."""
    return {
        **dataclasses.asdict(c),
        "mlp_params": c.mlp_params,
        "params": c.params,
        "act_bytes_per_sample": arch.act_bytes_per_sample(cfg, p.numerics),
        "tile_bytes_per_sample": arch.tile_bytes_per_sample(cfg, p.numerics),
        "ops_per_sample": per,
    }


def cost_report(
    cfg: TrainConfig,
    platform: Platform | None = None,
    *,
    samples_per_pixel: float = 13.0,
    n_images: int | None = None,
    clients: int = 4,
    run: RunSamples | None = None,
    grid_rule: arch.GridRule = arch.DEFAULT_GRID_RULE,
) -> dict:
    """The whole cost of ``cfg`` on ``platform`` (default GAP9) as a JSON-able nested dict.

    Args:
        cfg: the trainer configuration.
        platform: target; default :func:`load_platform` (gap9/gap9.yaml).
        samples_per_pixel: average samples per ray after empty-space skipping (paper: 13); sets
            rays per tile and the render cost.
        n_images: training images the drone stores in L3 (default ``cfg.train_images``).
        clients: drones of a federated round (for the per-round link time).
        run: what the run's steps worked on (compaction's trained share, the visual hull's
            share of the grid); default :class:`RunSamples` (neither).
        grid_rule: when the grid is updated (:data:`arch.GridRule`): the trainer's rule, or
            "fixed" (the paper's GAP9 run).
    Returns:
        {"config", "platform", "counts", "memory", "ops", "latency", "l3_traffic", "energy",
        "link", "verdicts"}; bytes, ops, seconds, joules.
    """
    p = _platform(platform)
    spp = float(samples_per_pixel)
    if spp <= 0 or cfg.tile_samples <= 0 or cfg.batch_samples <= 0:
        raise ValueError("samples_per_pixel, tile_samples and batch_samples must be positive")
    n_img = cfg.train_images if n_images is None else int(n_images)
    c = arch.counts(cfg, p.hash_rows)
    phases = l2_phases(cfg, p, spp)
    l2_phase = max(phases, key=phases.get)
    l1, l3 = l1_peak(cfg, p), l3_resident(cfg, p, n_img)
    total = total_memory(cfg, p)
    run = run if run is not None else RunSamples()
    sched = arch.grid_schedule(cfg, run.hull_fraction, grid_rule)
    ops = step_ops(cfg, p, spp, run, sched)
    per = arch.ops_per_sample(cfg)
    lat = latency(cfg, p, spp, run, sched)
    traffic = l3_traffic(cfg, p, spp, sched)
    verdicts = {
        "l1": {"need": l1["bytes"] + p.l1_reserved_bytes, "have": p.l1_bytes},
        "l2": {"need": phases[l2_phase], "have": p.l2_bytes},
        "l3": {"need": l3["total"], "have": p.l3_bytes},
        "untiled_total_in_l3": {"need": total["total"], "have": p.l3_bytes},
    }
    for v in verdicts.values():
        v["fits"] = v["need"] <= v["have"]
    return {
        "config": {k: getattr(cfg, k) for k in _CONFIG_FIELDS},
        "platform": p.name,
        "assumptions": {
            "samples_per_pixel": spp,
            "n_images": n_img,
            "hash_rows": p.hash_rows,
            **dataclasses.asdict(run),
            "grid_rule": grid_rule,
            "grid_updates": {"warmup": sched.warmup_updates, "steady": sched.steady_updates},
        },
        "counts": _counts(cfg, p, c, per),
        "memory": {
            "untiled": total,
            "l1_peak": l1,
            "l2_peak": {"bytes": phases[l2_phase], "phase": l2_phase, "phases": phases},
            "l3": l3,
            "largest_tile_in_l2": largest_tile_in_l2(cfg, p, spp),
        },
        "ops": {
            "step": ops,
            "frame": frame_samples(cfg, spp) * sum(per["forward"].values()),
        },
        "latency": lat,
        "l3_traffic": traffic,
        "energy": energy_report(lat, traffic, cfg.steps, p),
        "link": link_report(cfg, p, clients),
        "verdicts": verdicts,
    }
