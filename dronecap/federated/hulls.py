"""The drones' visual hulls: the global model's grid is rebuilt inside all of them.

The server's trainer holds the coordinator's shard only, so the global model's occupancy grid
was rebuilt inside the coordinator's visual hull (:func:`dronecap.federated.run.rebuild_grid`).
On viewpoint sectors that hull is carved by one sector's silhouettes and keeps cells that only
the other sectors' views carve away; the hash table's values there render as floaters in those
views. Lego, 4 drones, the default sector run (40 views): 29.36 dB as recorded, 31.73 with the
grid rebuilt inside the intersection of the four drones' hulls (central 31.70; IID 32.13 either
way; docs/federated.md "Session 17").

Each drone sends its hull once per run start, with its reply to the server's discovery query:
bool [R^3] packed to bits and deflated (lego, 64^3 cells: 4.1-4.5 kB). The server intersects
the ones it accepts with its own. A hull is refused (logged, the run goes on without it) when
it is not a packed bool grid of the server's size, or when it would leave less than
:data:`MIN_KEPT` of the coordinator's hull: under an intersection one drone sending an empty
hull would erase the global model's grid.
"""

from __future__ import annotations

import logging
from typing import Any

import numpy as np
from flwr.app import ArrayRecord

from dronecap.federated.fedavg import decode_array, encode_array

HULL_KEY = "hull"
# a drone's hull must keep at least this share of the coordinator's hull cells (lego sector
# shards: each drone's hull keeps 79-100 % of the coordinator's, their intersection 79 %)
MIN_KEPT = 0.5

log = logging.getLogger("dronecap.federate")


def hull_record(allowed: Any) -> ArrayRecord:
    """A trainer's hull (``grid.allowed``: bool tensor [R^3], or None: no hull) as the record a
    drone sends; empty when it has none."""
    if allowed is None:
        return ArrayRecord({})
    bits = np.packbits(allowed.cpu().numpy().astype(bool))
    return ArrayRecord({HULL_KEY: encode_array(bits, level=9)})


def intersect(own: Any, received: dict[int, ArrayRecord]) -> tuple[Any, dict[int, str]]:
    """``own`` (the coordinator's hull, bool tensor [R^3], or None) intersected with every
    acceptable hull of ``received`` (partition id -> the drone's hull record).

    Returns the new hull (``own`` itself when nothing was accepted) and the refusals
    (partition id -> reason). A drone without a hull (no silhouettes) adds nothing.
    """
    import torch

    if own is None:
        return own, {}
    cells = own.numel()
    out, refused = own.clone(), {}
    for k, record in sorted(received.items()):
        if HULL_KEY not in record:
            continue
        try:
            bits = decode_array(record[HULL_KEY])
        except Exception as err:  # noqa: BLE001 - any undecodable payload is a refusal
            refused[k] = f"hull not decodable ({type(err).__name__})"
            continue
        if bits.dtype != np.uint8 or bits.ndim != 1 or bits.size != (cells + 7) // 8:
            refused[k] = f"hull of {bits.size} {bits.dtype} values, expected {(cells + 7) // 8}"
            continue
        hull = torch.from_numpy(np.unpackbits(bits)[:cells].astype(bool)).reshape(own.shape)
        hull = hull.to(own.device)
        kept = int((hull & own).sum()) / max(int(own.sum()), 1)
        if kept < MIN_KEPT:
            refused[k] = f"hull keeps {kept:.0%} of the coordinator's (< {MIN_KEPT:.0%})"
            continue
        out &= hull
    for k, why in refused.items():
        log.warning("drone %s's hull refused: %s", k, why)
    return out, refused


def restrict_to_hulls(trainer: Any, received: dict[int, ArrayRecord]) -> dict[int, str]:
    """Restrict ``trainer``'s grid (the server's, for the global model) to the intersection of
    its hull with the drones' accepted ones (:func:`intersect`); returns the refusals."""
    from dronecap.nerf import occupancy

    allowed, refused = intersect(trainer.grid.allowed, received)
    if allowed is not None:
        trainer.grid = occupancy.restrict(trainer.grid, allowed)
    return refused
