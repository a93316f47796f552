"""Sparse downloads: the server sends the change of the global model, each drone keeps its copy.

Every drone holds the same *replica* of the global model: the model it starts a round from.
After a round the server encodes the change from the replica to its new model (after the
server step) with the upload codec (:func:`dronecap.federated.sparse.encode_update`: the
``rows`` fraction of most changed hash-table rows at ``bits`` bits, the MLPs at 8 bits) and
both sides add the decoded change to their replica with the same float32 operation
(:func:`dronecap.federated.fedavg.decode_reply`), so server and drones stay bit-identical. The
new replica *is* the new global model (:class:`~dronecap.federated.fedavg.DroneFedAvg`): what
was not sent is dropped, and the FedAvgM momentum carries it into later rounds. Keeping it in
the server's model instead (error feedback) made the model drift: drones start from the replica,
so every round they re-learn the changes they have not received, and the server added them
again each time (measured in docs/federated.md).

A drone can take the change only if it holds the replica it applies to: the one of the
previous round, which it saved when it trained that round. The server knows who does (the
drones that replied in that round); every other drone (round 1, a drone back after a failure)
gets the whole replica, losslessly (:func:`whole_record`). The config key :data:`BASE_KEY`
tells a drone which: the round whose replica the change applies to, or -1 for a whole one.
Only the model travels this way; an exchanged occupancy grid goes whole every round.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from flwr.app import ArrayRecord, RecordDict

from dronecap.federated.fedavg import (
    MODEL,
    decode_reply,
    encode_array,
    from_record,
    pack_update,
    to_record,
    unpack_update,
)
from dronecap.files import atomic_output

if TYPE_CHECKING:
    from dronecap.federated.state import FedSettings

BASE_KEY = "base-round"  # ConfigRecord key: round of the replica a change applies to; -1: whole


def whole_record(replica: Mapping[str, np.ndarray]) -> ArrayRecord:
    """The replica ``{name: float32 array}`` as whole arrays, losslessly compressed: in fp16
    where every value is an fp16 number (the pretrained model's, broadcast in round 1), else
    float32."""
    out = {}
    for name, a in replica.items():
        half = a.astype(np.float16)
        exact = np.array_equal(half.astype(np.float32), a)
        out[MODEL + name] = encode_array(half if exact else np.asarray(a, np.float32))
    return ArrayRecord(out)


def apply_record(
    record: ArrayRecord, replica: Mapping[str, np.ndarray] | None
) -> dict[str, np.ndarray]:
    """The new replica from a broadcast's model arrays: ``replica`` plus the sparse change, or
    the whole arrays (``replica`` None). Returns ``{name: float32 array}``; raises ValueError
    on a change that does not fit ``replica``."""
    model = ArrayRecord({k: v for k, v in record.items() if k.startswith(MODEL)})
    base = {MODEL + k: v for k, v in (replica or {}).items()}
    decoded, _ = decode_reply(model, base)
    return {k[len(MODEL) :]: np.asarray(v, np.float32) for k, v in decoded.items()}


class Downlink:
    """The server's side: the replica every drone holds, and what each drone is sent.

    ``replica``: ``{name: float32 array}`` the model the drones start round ``round + 1``
    from; ``holders``: the drones (any hashable id) that hold the replica of round
    ``round - 1`` (those the change applies to); ``rows``/``bits``: the change's codec.
    """

    def __init__(
        self,
        replica: Mapping[str, np.ndarray],
        round_: int,
        holders: set,
        rows: float,
        bits: int,
    ) -> None:
        self.replica = {k: np.asarray(v, np.float32) for k, v in replica.items()}
        self.round = round_
        self.holders = set(holders)
        self.rows, self.bits = rows, bits
        self.change: ArrayRecord | None = None  # the change from round - 1's replica

    @classmethod
    def start(cls, model: Mapping[str, np.ndarray], rows: float, bits: int) -> Downlink:
        """Before round 1: the replica is ``model`` rounded to fp16 (sent whole to all)."""
        half = {k: np.asarray(v, np.float16).astype(np.float32) for k, v in model.items()}
        return cls(half, 0, set(), rows, bits)

    def record_for(self, drone: object) -> tuple[ArrayRecord, int]:
        """What ``drone`` is sent this round: (the change, its base round) if it holds the
        previous replica, else (the whole replica, -1)."""
        if self.change is not None and drone in self.holders:
            return self.change, self.round - 1
        return whole_record(self.replica), -1

    def advance(self, model: Mapping[str, np.ndarray], holders: set) -> None:
        """After round ``round + 1``: encode ``model`` (the new global model, float32) as a
        change from the replica, apply it; ``holders``: the drones that took part in that round
        (they hold this round's replica now)."""
        from dronecap.federated.sparse import encode_update

        arrays, _ = encode_update(model, self.replica, {}, self.rows, self.bits)
        self.change = ArrayRecord({MODEL + k: v for k, v in arrays.items()})
        self.replica = apply_record(self.change, self.replica)
        self.round += 1
        self.holders = set(holders)

    @classmethod
    def for_run(
        cls, s: FedSettings, history: list[dict], current: Mapping[str, np.ndarray]
    ) -> Downlink | None:
        """The server's downlink after the last round in ``history`` (None: the run broadcasts
        whole arrays). ``current``: the global model as packed arrays; after round 0 the
        replica is its fp16 rounding, later it is the global model itself. A resumed run
        sends every drone the whole model once."""
        if not (s.quant_bits and s.down_rows):
            return None
        model, last = unpack_update(current)[0], history[-1]["round"]
        if last == 0:
            return cls.start(model, s.down_rows, s.quant_bits)
        return cls(model, last, set(), s.down_rows, s.quant_bits)


def replica_file(folder: Path, r: int) -> Path:
    """``folder/replica_RRR.npz``: a drone's replica, the model it started round ``r + 1``
    from."""
    return Path(folder) / f"replica_{r:03d}.npz"


def broadcast(
    s: FedSettings, current: Mapping[str, np.ndarray], downlink: Downlink | None
) -> ArrayRecord:
    """The arrays every drone is sent: the global model (and exchanged grid) as whole arrays,
    or with a ``downlink`` the grid only (the strategy adds each drone's model change)."""
    model, grid = unpack_update(current)
    return to_record(pack_update({} if downlink else model, grid, s.transfer_dtype), s.compress)


def receive(content: RecordDict, folder: Path, r: int) -> dict[str, np.ndarray]:
    """The drone's side: the global model (and exchanged grid) it starts round ``r`` from,
    as packed arrays. Whole arrays as sent, or with sparse downloads (config :data:`BASE_KEY`)
    its replica of that round plus the change sent, saved as its replica of round ``r - 1``
    in ``folder``."""
    record, config = content["arrays"], content["config"]
    if BASE_KEY not in config:
        return from_record(record)
    base = int(config[BASE_KEY])
    replica = None
    if base >= 0:
        if not replica_file(folder, base).exists():
            raise RuntimeError(f"the change sent applies to round {base}'s model, not kept here")
        with np.load(replica_file(folder, base)) as z:
            replica = {k: z[k] for k in z.files}
    model = apply_record(record, replica)
    with atomic_output(replica_file(folder, r - 1)) as tmp:
        with open(tmp, "wb") as f:
            np.savez(f, **model)
    rest = from_record(ArrayRecord({k: v for k, v in record.items() if not k.startswith(MODEL)}))
    return {**rest, **{MODEL + k: v for k, v in model.items()}}
