"""FedAvg for Tiny-DroNeRF: what a drone sends, how updates are averaged, and what it costs.

A drone's update is a flat ``{name: array}`` dict. Model parameters (hash table + MLPs, the
trainer's ``model_weights()``) are keyed ``model/<name>``; the occupancy grid (the trainer's
``grid_state()``), only when it is exchanged, is keyed ``grid/<name>``. Floating arrays travel in
the transfer dtype (fp32 or fp16); the server averages them in float32 with Flower's FedAvg,
weighted by each drone's train-image count. Integer and boolean arrays (e.g. a grid's occupancy
bits) never travel: a drone rebuilds them from the densities it receives.

Optionally (``compress``) every array travels losslessly compressed (:func:`encode_array`): its
bytes regrouped by significance (all first bytes, then all second bytes, ...) and deflated.
fp16 hash-table entries share few exponents, so the high bytes compress well: a trained
tiny-dronerf update shrinks by ~14 %, which brings it under the paper's 0.52 MB with the MLPs.

Byte accounting is exact: :func:`payload_bytes` sums the serialised size of every object Flower
transmits for a message's content (its record dict, array records, array headers and data
chunks, each as ``deflate()`` produces it), so it is what goes through the SuperLink, not an
estimate from array sizes.
"""

from __future__ import annotations

import zlib
from collections.abc import Iterable, Mapping
from typing import TYPE_CHECKING, Any

import numpy as np
from flwr.app import Array, ArrayRecord, ConfigRecord, Message, MetricRecord, RecordDict
from flwr.serverapp.strategy import FedAvgM

from dronecap.federated.sparse import TABLE

if TYPE_CHECKING:
    from dronecap.federated.downlink import Downlink

MODEL = "model/"
GRID = "grid/"
TRANSFER_DTYPES = {"fp32": np.float32, "fp16": np.float16}
WEIGHT_KEY = "num-examples"  # MetricRecord key FedAvg weights by: the drone's train images


def pack_update(
    model: Mapping[str, np.ndarray],
    grid: Mapping[str, np.ndarray] | None,
    transfer_dtype: str = "fp32",
) -> dict[str, np.ndarray]:
    """The arrays one drone sends: model parameters, plus the grid's floating arrays if given.

    ``model`` and ``grid`` map names to arrays of any shape; floating arrays are cast to
    ``transfer_dtype`` ("fp32" or "fp16"); non-floating grid arrays are left out (derived data).
    """
    if transfer_dtype not in TRANSFER_DTYPES:
        raise ValueError(f"transfer dtype {transfer_dtype!r}; known: {sorted(TRANSFER_DTYPES)}")
    dtype = TRANSFER_DTYPES[transfer_dtype]
    out: dict[str, np.ndarray] = {}
    for prefix, part in ((MODEL, model), (GRID, grid or {})):
        for name, arr in part.items():
            a = np.asarray(arr)
            if prefix == GRID and not np.issubdtype(a.dtype, np.floating):
                continue
            out[prefix + name] = np.ascontiguousarray(a.astype(dtype, copy=False))
    return out


def unpack_update(
    arrays: Mapping[str, np.ndarray],
) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray]]:
    """Split received arrays back into (model, grid) dicts, floating arrays as float32."""
    model: dict[str, np.ndarray] = {}
    grid: dict[str, np.ndarray] = {}
    for key, arr in arrays.items():
        a = np.asarray(arr)
        if np.issubdtype(a.dtype, np.floating):
            a = a.astype(np.float32, copy=False)
        if key.startswith(MODEL):
            model[key[len(MODEL) :]] = a
        elif key.startswith(GRID):
            grid[key[len(GRID) :]] = a
        else:
            raise KeyError(f"unexpected array {key!r} in a federated update")
    return model, grid


def weighted_mean(
    updates: list[Mapping[str, np.ndarray]], weights: list[float]
) -> dict[str, np.ndarray]:
    """Reference FedAvg: ``sum_k w_k x_k / sum_k w_k`` per array, computed in float64.

    ``updates[k][name]`` has the same shape for every k; returns float32 arrays.
    """
    if not updates or len(updates) != len(weights):
        raise ValueError("need one weight per update and at least one update")
    total = float(sum(weights))
    return {
        name: (
            sum(
                np.asarray(u[name], np.float64) * (w / total)
                for u, w in zip(updates, weights, strict=True)
            )
        ).astype(np.float32)
        for name in updates[0]
    }


CODEC = "dronecap.shuffle-deflate"  # Flower ``Array.stype`` of a compressed array


def encode_array(a: np.ndarray, level: int = 6) -> Array:
    """A Flower Array holding ``a`` losslessly compressed: byte-shuffled, then deflated.

    ``a``: any shape and fixed-size dtype. Byte ``j`` of every element comes before byte
    ``j + 1`` of any element, so the slowly varying sign/exponent bytes form long runs that
    deflate (``zlib`` at ``level``) can code in few bits. :func:`decode_array` inverts it.
    """
    a = np.ascontiguousarray(a)
    shuffled = a.reshape(-1).view(np.uint8).reshape(-1, a.itemsize).T.tobytes()
    shape = tuple(int(n) for n in a.shape)
    return Array(dtype=str(a.dtype), shape=shape, stype=CODEC, data=zlib.compress(shuffled, level))


def decode_array(arr: Array) -> np.ndarray:
    """The numpy array of a received Flower Array, plain or :func:`encode_array`-compressed."""
    if arr.stype != CODEC:
        return arr.numpy()
    dtype = np.dtype(arr.dtype)
    planes = np.frombuffer(zlib.decompress(arr.data), np.uint8).reshape(dtype.itemsize, -1)
    return np.ascontiguousarray(planes.T).view(dtype).reshape(arr.shape)


def to_record(arrays: Mapping[str, np.ndarray], compress: bool = False) -> ArrayRecord:
    """Wrap arrays for a Flower message: as .npy bytes, or with ``compress`` as
    :func:`encode_array` does."""
    wrap = encode_array if compress else (lambda v: Array(np.ascontiguousarray(v)))
    return ArrayRecord({k: wrap(v) for k, v in arrays.items()})


def from_record(record: ArrayRecord) -> dict[str, np.ndarray]:
    """The numpy arrays of a received ArrayRecord (compressed or not), dtypes as sent."""
    return {k: decode_array(v) for k, v in record.items()}


def payload_bytes(content: RecordDict) -> int:
    """Exact bytes Flower serialises for a message's content.

    The sum of ``len(obj.deflate())`` over every distinct object of the content tree (record
    dict, records, array headers, array data chunks), as Flower's object store transmits them.
    """
    seen: set[str] = set()
    stack: list[Any] = [content]
    total = 0
    while stack:
        obj = stack.pop()
        if obj.object_id in seen:
            continue
        seen.add(obj.object_id)
        total += len(obj.deflate())
        stack.extend((obj.children or {}).values())
    return total


def array_data_bytes(arrays: Mapping[str, np.ndarray]) -> int:
    """Raw tensor bytes (no headers): sum of ``arr.nbytes``."""
    return int(sum(np.asarray(a).nbytes for a in arrays.values()))


class DroneFedAvg(FedAvgM):
    """Flower's FedAvgM strategy with checked, decoded, visibility-weighted aggregation.

    Flower samples the drones and builds the messages (``configure_train``); the aggregation is
    this class's: each reply is decoded (plain, :func:`encode_array`-compressed, or a
    :mod:`~dronecap.federated.sparse` delta against the model broadcast this round), screened
    (:func:`dronecap.federated.checks.screen`: a bad update is left out with a reason), and
    averaged in float32 (:func:`masked_mean`). The weights are the train-image counts the
    server knows (``known_examples``, node id -> count), never the self-reported ones. With
    ``visibility`` each hash-table row is averaged over the drones that sent it only. Then,
    with ``server_learning_rate`` != 1 or ``server_momentum`` > 0, FedAvgM's server step
    ``m <- momentum * m + (x - avg)``, ``x <- x - lr * m`` (Hsu et al. 2019) from the float32
    global model ``self.current_arrays`` (set by :meth:`resume`); defaults (1, 0) are plain
    FedAvg. With ``table_step`` "mean" the hash table skips that step and takes the mean change
    itself: a row seen by one drone (visibility-weighted, a swarm's drone shards) is that drone's
    own change, which a server step of 2 would double. After each
    ``configure_train``/``aggregate_train``, ``self.last_round`` holds
    ``bytes_down`` (per destination node), ``bytes_up`` (per replying node) and ``failed``
    (node id -> reason).
    """

    def __init__(
        self,
        visibility: bool = False,
        downlink: Downlink | None = None,
        table_step: str = "server",
        **kwargs: Any,
    ) -> None:
        kwargs.setdefault("weighted_by_key", WEIGHT_KEY)
        kwargs.setdefault("fraction_evaluate", 0.0)  # the global model is tested server-side
        super().__init__(**kwargs)
        self.visibility = visibility
        self.downlink = downlink
        self.table_step = table_step
        self.known_examples: dict[int, int] = {}
        self.base: dict[str, np.ndarray] = {}
        self.last_round: dict[str, Any] = {"bytes_down": {}, "bytes_up": {}, "failed": {}}

    def configure_train(self, server_round, arrays, config, grid) -> Iterable[Message]:
        """Flower's messages of a round; with a ``downlink`` (sparse downloads) each drone's
        model arrays are replaced by what :meth:`Downlink.record_for` sends it, and ``arrays``
        carries only the rest (an exchanged grid). ``self.base`` becomes the model the drones
        start from (their updates are decoded against it)."""
        from dronecap.federated.downlink import BASE_KEY

        messages = list(super().configure_train(server_round, arrays, config, grid))
        self.base = {k: v.astype(np.float32) for k, v in from_record(arrays).items()}
        if self.downlink is not None:
            self.base.update({MODEL + k: v for k, v in self.downlink.replica.items()})
            for m in messages:
                model, base_round = self.downlink.record_for(m.metadata.dst_node_id)
                record = ArrayRecord({**dict(arrays.items()), **dict(model.items())})
                own = ConfigRecord({**dict(config.items()), BASE_KEY: base_round})
                m.content = RecordDict({self.arrayrecord_key: record, self.configrecord_key: own})
        down = {m.metadata.dst_node_id: payload_bytes(m.content) for m in messages}
        self.last_round = {"bytes_down": down, "bytes_up": {}, "failed": {}}
        return messages

    def aggregate_train(  # noqa: D102
        self, server_round: int, replies: Iterable[Message]
    ) -> tuple[ArrayRecord | None, MetricRecord | None]:
        from dronecap.federated.checks import screen

        failed = self.last_round["failed"]
        base = self.base or from_record(self.current_arrays)
        models: dict[int, dict[str, np.ndarray]] = {}
        masks: dict[int, dict[str, np.ndarray]] = {}
        claimed: dict[int, float] = {}
        for msg in replies:
            node = msg.metadata.src_node_id
            if msg.has_error():
                failed[node] = msg.error.reason
                continue
            self.last_round["bytes_up"][node] = payload_bytes(msg.content)
            try:
                count = float(msg.content["metrics"][self.weighted_by_key])
                model, mask = decode_reply(msg.content[self.arrayrecord_key], base)
            except (KeyError, TypeError, ValueError) as err:
                failed[node] = f"unreadable update: {err}"
                continue
            models[node], masks[node], claimed[node] = model, mask, count
        known = {n: float(self.known_examples.get(n, claimed[n])) for n in models}
        failed.update(screen(models, base, claimed, known))
        ok = [n for n in models if n not in failed]
        if not ok:
            return None, None
        deltas = {n: {k: models[n][k].astype(np.float64) - base[k] for k in base} for n in ok}
        weights = {n: float(known[n]) for n in ok}
        vis = {n: masks[n] for n in ok} if self.visibility else {}
        avg = masked_mean(deltas, weights, vis)
        x = from_record(self.current_arrays) if self.current_arrays is not None else base
        new = self._server_step(x, {k: (x[k] + avg[k]).astype(np.float32) for k in base})
        if self.downlink is not None:  # the global model is what the drones will hold
            self.downlink.advance(unpack_update(new)[0], set(self.last_round["bytes_up"]))
            new.update({MODEL + k: v for k, v in self.downlink.replica.items()})
        self.current_arrays, self.base = to_record(new), new
        return to_record(new), MetricRecord({"participants": len(ok)})

    def _server_step(
        self, x: dict[str, np.ndarray], avg: dict[str, np.ndarray]
    ) -> dict[str, np.ndarray]:
        """FedAvgM's step from the global model ``x`` towards ``avg``, the global model plus
        the drones' mean change (plain FedAvg, ``avg`` itself, with lr 1 and no momentum)."""
        if not self.server_opt:
            return avg
        grad = [x[k] - avg[k] for k in x]
        mean_only = {MODEL + TABLE} if self.table_step == "mean" else set()
        grad = [np.zeros_like(g) if k in mean_only else g for k, g in zip(x, grad, strict=True)]
        if self.server_momentum > 0.0:
            if self.momentum_vector is not None:
                grad = [
                    self.server_momentum * m + g
                    for m, g in zip(self.momentum_vector, grad, strict=True)
                ]
            self.momentum_vector = grad
        return {
            k: avg[k] if k in mean_only else x[k] - self.server_learning_rate * g
            for k, g in zip(x, grad, strict=True)
        }

    def server_state(self) -> dict[str, np.ndarray]:
        """The server optimizer's momentum ``{name: array}`` (empty before the first step or
        without momentum), to save beside the global model for a resume."""
        if self.momentum_vector is None or self.current_arrays is None:
            return {}
        return dict(zip(self.current_arrays.keys(), self.momentum_vector, strict=True))

    def resume(self, current: Mapping[str, np.ndarray], momentum: Mapping[str, np.ndarray]) -> None:
        """Start or continue a run from the float32 global model ``current`` (not its fp16 or
        compressed wire copy) and the saved ``momentum`` (:meth:`server_state`; empty: none)."""
        self.base = {k: np.asarray(v, np.float32) for k, v in current.items()}
        self.current_arrays = to_record(self.base)
        self.momentum_vector = [np.asarray(momentum[k]) for k in current] if momentum else None


def decode_reply(
    record: ArrayRecord, base: Mapping[str, np.ndarray]
) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray]]:
    """A drone's model from its reply and the rows it sent.

    ``record``: the reply's arrays, each plain, compressed (:func:`encode_array`) or a sparse
    delta (:func:`dronecap.federated.sparse.encode_delta`) against ``base`` (the model
    broadcast this round, float32). Returns ``(model, masks)``: {name: array} (dtype as sent
    for plain arrays, float32 for deltas) and {name: bool [rows] mask of the rows sent} for the
    sparse arrays. Raises ValueError on a malformed or mismatched array."""
    from dronecap.federated.sparse import SPARSE, decode_delta

    model: dict[str, np.ndarray] = {}
    masks: dict[str, np.ndarray] = {}
    for key, arr in record.items():
        if arr.stype != SPARSE:
            model[key] = decode_array(arr)
            continue
        if key not in base or tuple(arr.shape) != base[key].shape:
            raise ValueError(f"sparse {key} of shape {tuple(arr.shape)} matches no model array")
        delta, masks[key] = decode_delta(arr)
        model[key] = base[key] + delta
    return model, masks


def masked_mean(
    deltas: Mapping[int, Mapping[str, np.ndarray]],
    weights: Mapping[int, float],
    masks: Mapping[int, Mapping[str, np.ndarray]],
) -> dict[str, np.ndarray]:
    """Weighted mean of the drones' changes, row by row over the drones that sent each row.

    ``deltas``: drone -> {name: change [rows, ...]}; ``weights``: drone -> weight > 0
    (all zero or negative: equal weights); ``masks``: drone -> {name: bool [rows]} rows that
    drone sent (a name or drone without a mask: every row). Row i of ``name`` is
    ``sum_k w_k m_ki d_ki / sum_k w_k m_ki`` (0 where no drone sent it). Returns float64.
    """
    drones = list(deltas)
    w = np.array([max(float(weights[k]), 0.0) for k in drones], np.float64)
    w = w if w.sum() > 0 else np.ones_like(w)
    out: dict[str, np.ndarray] = {}
    for name in deltas[drones[0]]:
        shape = deltas[drones[0]][name].shape
        num = np.zeros(shape, np.float64)
        den = np.zeros(shape[:1] if shape else (), np.float64)
        for wk, k in zip(w, drones, strict=True):
            m = masks.get(k, {}).get(name)
            num += wk * deltas[k][name]
            den = den + (wk * m if m is not None else wk)
        den = den.reshape(den.shape + (1,) * (len(shape) - den.ndim))
        out[name] = np.where(den > 0, num / np.where(den > 0, den, 1.0), 0.0)
    return out
