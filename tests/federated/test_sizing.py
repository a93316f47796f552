"""The federated model is resolved once, on the union of the shards, within the GAP9 budget."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from dronecap.datasets.format import write_dataset
from dronecap.datasets.shard import shard_dataset
from dronecap.errors import InputError
from dronecap.federated.baselines import union_train
from dronecap.federated.sizing import resolve_once
from dronecap.federated.state import train_split
from dronecap.gap9.model import memory_bytes
from dronecap.nerf.config import SIZED_FIELDS, preset
from dronecap.nerf.resolve import resolve
from dronecap.nerf.trainer import Trainer


@pytest.fixture(scope="module")
def cube_shards(tmp_path_factory, make_cube):
    folder = tmp_path_factory.mktemp("fed_sizing")
    write_dataset(folder / "cube.h5", make_cube(n=24))
    shard_dataset(folder / "cube.h5", folder / "shards", 2, "sector")
    return sorted((folder / "shards").glob("client_*.h5"))


def test_sized_preset_is_resolved_once_within_the_gap9_budget(cube_shards):
    sized = preset("scene-sized")
    once = resolve_once(sized, cube_shards)
    union = resolve(sized, union_train([str(p) for p in cube_shards]), memory_fn=memory_bytes)
    for k in SIZED_FIELDS:
        assert getattr(once.config, k) == getattr(union.config, k)
    assert not once.config.sized and not once.config.auto_n_max
    # on a drone's own shard and without the budget the table kept the preset's 2^13 rows
    alone = resolve(sized, train_split(cube_shards[0])).config
    assert once.config.log2_hashmap > alone.log2_hashmap == sized.log2_hashmap
    assert memory_bytes(once.config) <= sized.budget_mb * 1e6
    # every drone builds the very same model from the fixed configuration
    shapes = []
    for path in cube_shards:
        tr = Trainer(once.config, train_split(path))
        assert all(getattr(tr.cfg, k) == getattr(once.config, k) for k in SIZED_FIELDS)
        shapes.append({k: v.shape for k, v in tr.field.state_dict().items()})
    assert shapes[0] == shapes[1]


def test_shards_of_other_scenes_are_refused(cube_shards, tmp_path, make_cube):
    other = make_cube(n=8)
    other = dataclasses.replace(other, kind="shard", aabb=np.asarray(other.aabb) * 2)
    write_dataset(tmp_path / "client_1.h5", other)
    with pytest.raises(InputError, match="other scene bounds than client_0.h5"):
        resolve_once(preset("scene-sized"), [cube_shards[0], tmp_path / "client_1.h5"])
