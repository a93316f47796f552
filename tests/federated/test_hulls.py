"""The drones' visual hulls (federated/hulls.py): sent packed, intersected by the server,
refused when malformed or when they would erase most of the coordinator's hull."""

from __future__ import annotations

import numpy as np
import torch
from flwr.app import Array, ArrayRecord

from dronecap.federated.hulls import HULL_KEY, MIN_KEPT, hull_record, intersect


def _hull(shape: tuple[int, ...], keep: slice) -> torch.Tensor:
    h = torch.zeros(shape, dtype=torch.bool).reshape(-1)
    h[keep] = True
    return h.reshape(shape)


def test_the_server_keeps_the_cells_every_accepted_drone_keeps():
    own = _hull((8, 8, 8), slice(0, 400))  # the coordinator's hull: 400 of 512 cells
    narrower = _hull((8, 8, 8), slice(100, 512))  # keeps 300 of them (75 %)
    empty = _hull((8, 8, 8), slice(0, 0))  # a drone erasing everything
    sent = {1: hull_record(narrower), 2: hull_record(empty), 3: hull_record(None)}
    assert len(sent[3]) == 0 and HULL_KEY in sent[1]
    # packed to bits and deflated: far below a byte per cell
    assert len(sent[1][HULL_KEY].data) < 512 // 8
    out, refused = intersect(own, sent)
    assert torch.equal(out, own & narrower) and int(out.sum()) == 300
    assert set(refused) == {2} and f"< {MIN_KEPT:.0%}" in refused[2]
    assert torch.equal(own, _hull((8, 8, 8), slice(0, 400)))  # the input is not changed


def test_malformed_hulls_are_refused_and_no_hull_changes_nothing():
    own = _hull((4, 4, 4), slice(0, 64))
    wrong_size = ArrayRecord({HULL_KEY: Array(np.zeros(3, np.uint8))})
    wrong_dtype = ArrayRecord({HULL_KEY: Array(np.zeros(8, np.float32))})
    garbage = ArrayRecord(
        {HULL_KEY: Array(dtype="uint8", shape=(8,), stype="dronecap.shuffle-deflate", data=b"x")}
    )
    out, refused = intersect(own, {1: wrong_size, 2: wrong_dtype, 3: garbage})
    assert torch.equal(out, own) and sorted(refused) == [1, 2, 3]
    assert intersect(None, {1: hull_record(own)}) == (None, {})  # a server without a hull
