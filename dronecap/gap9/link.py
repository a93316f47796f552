"""The federated link on GAP9: the model's bytes per round and the radio time to move them."""

from __future__ import annotations

from dronecap.gap9 import arch
from dronecap.gap9.platform import Platform, load_platform
from dronecap.nerf.config import TrainConfig


def federated_payload(cfg: TrainConfig, exchange_grid: bool, bytes_per_value: int = 2) -> int:
    """Bytes one drone sends (or receives) per round for the model: hash table + MLP weights,
    plus one value per occupancy cell when the grid is exchanged. Counts T rows per level, as
    the paper. tiny-dronerf, fp16: 524288 + 18816 = 543104 B; + 2 x 128^3 = 4737408 B."""
    c = arch.counts(cfg, "paper")
    values = c.params + (c.grid_cells if exchange_grid else 0)
    return values * bytes_per_value


def link_time_s(n_bytes: int, platform: Platform | None = None) -> float:
    """Seconds to move ``n_bytes`` over the radio at its rated bit rate (8 bits per byte).

    A FedAvg round over one shared channel moves every upload and download in turn: 4 drones x
    (up + down) x 0.52 MB -> 2.24 s at 15 Mbit/s.
    """
    p = platform if platform is not None else load_platform()
    return n_bytes * 8 / p.link_bits_per_s


def link_report(cfg: TrainConfig, p: Platform, clients: int) -> dict[str, float | int]:
    """A FedAvg round of ``clients`` drones (each uploads and downloads the model), without
    and with the occupancy grid exchanged: payload bytes, round bytes, round seconds."""
    no_grid, with_grid = federated_payload(cfg, False), federated_payload(cfg, True)
    transfers = 2 * clients
    return {
        "payload_no_grid": no_grid,
        "payload_grid": with_grid,
        "clients": clients,
        "round_bytes_no_grid": transfers * no_grid,
        "round_bytes_grid": transfers * with_grid,
        "round_s_no_grid": link_time_s(transfers * no_grid, p),
        "round_s_grid": link_time_s(transfers * with_grid, p),
    }
