"""The model every drone trains, decided once before the federation starts.

A sized preset (``scene-sized``) takes n_max, marching step, occupancy grid and hash-table size
from the scene (:mod:`dronecap.nerf.sizing`). Resolved on each drone's own shard, drones that
saw other views would build grids of other sizes, whose weights cannot be averaged, and
without the device budget the table would keep the preset's size. So ``dronecap federate``
resolves the configuration once, on the union of the shards' train frames and within the GAP9
memory budget (:func:`dronecap.gap9.model.memory_bytes`, as ``dronecap train`` does), and every
drone, the coordinator and the baselines build that fixed model.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

from dronecap.federated.baselines import union_train
from dronecap.nerf.config import TrainConfig
from dronecap.nerf.resolve import Resolved, resolve


def resolve_once(cfg: TrainConfig, shards: list[Path]) -> Resolved:
    """``cfg`` resolved once on the union of the train frames of ``shards`` (checked shard
    files) within the GAP9 budget; its ``config`` is fixed (nothing is left to size: every
    drone builds the same model from it).

    Raises:
        InputError: shards with other scene bounds than the first, or no sized model within
            the budget.
    """
    from dronecap.gap9.model import memory_bytes

    resolved = resolve(cfg, union_train([str(p) for p in shards]), memory_fn=memory_bytes)
    fixed = resolved.config.replace(sized=False, auto_n_max=False, sized_keep="")
    return dataclasses.replace(resolved, config=fixed)
