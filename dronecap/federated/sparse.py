"""Sparse, quantised model updates: what a drone sends instead of its whole model.

A drone sends its *change* ``delta = local - received`` (the global model it received this
round), plus the error-feedback residual of what it did not send before. Each array travels as a
Flower ``Array`` of ``stype`` :data:`SPARSE` (its ``shape`` and ``dtype`` are the full
array's) holding:

- the rows sent: for the hash table (``encoding.table``, [T_total, F]) only the ``rows``
  fraction of rows with the largest change (L2 norm over the row's features); for every other
  array (the MLPs' weights) all rows. Row numbers are delta-coded (uint32), byte-shuffled and
  deflated: consecutive rows cost a fraction of a byte each.
- their values quantised to ``bits`` (8 or 4) bits, symmetric, one fp16 scale per block of
  :data:`BLOCK` values (``scale = max|v| / (2^(bits-1) - 1)``), deflated.

What was not sent (unsent rows, rounding) stays in the drone's residual and is added to the
next round's change (error feedback, Seide et al. 2014; Karimireddy et al. 2019), so nothing is
lost over rounds, only delayed. The rows sent also tell the server which rows a drone changed
most: :func:`decode_delta` returns them as a mask, for visibility-weighted averaging.
"""

from __future__ import annotations

import struct
import zlib
from collections.abc import Mapping

import numpy as np
from flwr.app import Array

SPARSE = "dronecap.sparse-q"  # Flower ``Array.stype`` of a sparse quantised delta
TABLE = "encoding.table"  # the hash table's parameter name (Trainer.model_weights)
BLOCK = 64  # values per quantisation scale
MLP_BITS = 8  # bits of every non-table array (MLP weights)
_HEADER = struct.Struct("<BIII")  # bits, rows sent, index bytes, value bytes


def _rows2d(a: np.ndarray) -> np.ndarray:
    """``a`` as [rows, cols] (a 1-D array is one column)."""
    return a.reshape(a.shape[0], -1) if a.ndim >= 2 else a.reshape(-1, 1)


def select_rows(delta: np.ndarray, fraction: float) -> np.ndarray:
    """Sorted indices of the ``ceil(fraction * rows)`` rows of ``delta`` [rows, ...] with the
    largest L2 norm (all rows when ``fraction`` >= 1); non-finite norms count as largest."""
    d = _rows2d(delta)
    n = d.shape[0]
    k = n if fraction >= 1 else max(1, int(np.ceil(fraction * n)))
    if k >= n:
        return np.arange(n, dtype=np.int64)
    norm = np.nan_to_num(np.einsum("ij,ij->i", d, d, dtype=np.float64), nan=np.inf)
    return np.sort(np.argpartition(norm, n - k)[n - k :])


def quantise(values: np.ndarray, bits: int) -> tuple[np.ndarray, np.ndarray]:
    """Symmetric per-block quantisation of ``values`` (flat float) to ``bits`` (4 or 8).

    Returns ``(q, scales)``: int8 codes in [-(2^(bits-1)-1), 2^(bits-1)-1], one per value, and
    one fp16 scale per :data:`BLOCK` values. :func:`dequantise` inverts it up to rounding."""
    top = 2 ** (bits - 1) - 1
    v = np.asarray(values, np.float32).reshape(-1)
    pad = (-v.size) % BLOCK
    blocks = np.concatenate([v, np.zeros(pad, np.float32)]).reshape(-1, BLOCK)
    with np.errstate(over="ignore", invalid="ignore"):
        scales = (np.abs(blocks).max(axis=1) / top).astype(np.float16)
        s = scales.astype(np.float32)[:, None]
        q = np.where(s > 0, np.rint(blocks / np.where(s > 0, s, 1)), 0)
    q = np.clip(np.nan_to_num(q), -top, top).astype(np.int8).reshape(-1)[: v.size]
    return q, scales


def dequantise(q: np.ndarray, scales: np.ndarray) -> np.ndarray:
    """Float32 values of :func:`quantise` codes ``q`` [n] with their block ``scales``."""
    s = np.repeat(np.asarray(scales, np.float32), BLOCK)[: q.size]
    return q.astype(np.float32) * s


def _pack_codes(q: np.ndarray, bits: int) -> bytes:
    """int8 codes as bytes: one per code (8 bits) or two per byte (4 bits, offset by 8)."""
    if bits == 8:
        return q.tobytes()
    u = (q.astype(np.int16) + 8).astype(np.uint8)
    if u.size % 2:
        u = np.append(u, np.uint8(8))
    return (u[0::2] | (u[1::2] << 4)).tobytes()


def _unpack_codes(data: bytes, bits: int, n: int) -> np.ndarray:
    """Inverse of :func:`_pack_codes` for ``n`` codes."""
    if bits == 8:
        return np.frombuffer(data, np.int8)[:n].copy()
    b = np.frombuffer(data, np.uint8)
    u = np.empty(2 * b.size, np.int16)
    u[0::2], u[1::2] = b & 15, b >> 4
    return (u[:n] - 8).astype(np.int8)


def encode_delta(delta: np.ndarray, rows: np.ndarray, bits: int) -> tuple[Array, np.ndarray]:
    """One array's change as a :data:`SPARSE` Flower Array, and what the receiver will decode.

    ``delta``: float array [rows, ...]; ``rows``: sorted row indices to send (int);
    ``bits``: 8 or 4. Returns ``(array, sent)`` with ``sent`` the float32 array
    :func:`decode_delta` reconstructs (zero on unsent rows), for the error-feedback residual.
    """
    if bits not in (4, 8):
        raise ValueError(f"quantisation bits must be 4 or 8, got {bits}")
    d = _rows2d(np.asarray(delta, np.float32))
    q, scales = quantise(d[rows], bits)
    gaps = np.diff(np.asarray(rows, np.int64), prepend=-1).astype(np.uint32)
    index = zlib.compress(gaps.view(np.uint8).reshape(-1, 4).T.tobytes(), 9)
    values = zlib.compress(_pack_codes(q, bits) + scales.tobytes(), 9)
    blob = _HEADER.pack(bits, len(rows), len(index), len(values)) + index + values
    sent = np.zeros_like(d)
    sent[rows] = dequantise(q, scales).reshape(len(rows), d.shape[1])
    shape = tuple(int(n) for n in np.shape(delta))
    return Array(dtype="float32", shape=shape, stype=SPARSE, data=blob), sent.reshape(shape)


def decode_delta(arr: Array) -> tuple[np.ndarray, np.ndarray]:
    """``(delta, mask)`` of a :data:`SPARSE` Array: the float32 change (zero on rows not sent)
    and a bool [rows] mask of the rows sent.

    Raises:
        ValueError: a malformed array (bad header, row numbers out of range or not increasing,
            wrong value count).
    """
    shape = tuple(arr.shape)
    if not shape or any(n <= 0 for n in shape):
        raise ValueError(f"sparse array of shape {shape}")
    n_rows, cols = shape[0], int(np.prod(shape[1:], dtype=np.int64))
    data = arr.data
    try:
        bits, k, n_index, n_values = _HEADER.unpack_from(data)
        if bits not in (4, 8) or not 0 < k <= n_rows:
            raise ValueError(f"{bits} bits, {k} rows of {n_rows}")
        start = _HEADER.size
        gaps = zlib.decompress(data[start : start + n_index])
        raw = zlib.decompress(data[start + n_index : start + n_index + n_values])
    except (struct.error, zlib.error) as err:
        raise ValueError(f"malformed sparse array: {err}") from None
    if len(gaps) != 4 * k:
        raise ValueError(f"{len(gaps)} index bytes for {k} rows")
    rows = np.cumsum(np.frombuffer(gaps, np.uint8).reshape(4, k).T.copy().view(np.uint32)[:, 0])
    rows = rows.astype(np.int64) - 1
    if k > 1 and np.any(np.diff(rows) <= 0) or rows[0] < 0 or rows[-1] >= n_rows:
        raise ValueError("row numbers out of range or not increasing")
    n = k * cols
    code_bytes = n if bits == 8 else (n + 1) // 2
    n_scales = -(-n // BLOCK)
    if len(raw) != code_bytes + 2 * n_scales:
        raise ValueError(f"{len(raw)} value bytes for {n} values")
    q = _unpack_codes(raw[:code_bytes], bits, n)
    scales = np.frombuffer(raw[code_bytes:], np.float16)
    delta = np.zeros((n_rows, cols), np.float32)
    delta[rows] = dequantise(q, scales).reshape(k, cols)
    mask = np.zeros(n_rows, bool)
    mask[rows] = True
    return delta.reshape(shape), mask


def encode_update(
    local: Mapping[str, np.ndarray],
    received: Mapping[str, np.ndarray],
    residual: Mapping[str, np.ndarray],
    rows: float,
    bits: int,
    mlp_bits: int = MLP_BITS,
) -> tuple[dict[str, Array], dict[str, np.ndarray]]:
    """A drone's sparse quantised update and its new residual.

    ``local``/``received``: ``{name: array}`` model weights after local training and as received
    (same keys and shapes); ``residual``: the previous residual (empty: none). The table sends
    the ``rows`` fraction of its rows at ``bits`` bits, other arrays all rows at
    ``mlp_bits`` (8 or 4). Returns ``({name: Array}, {name: new residual})``.
    """
    arrays: dict[str, Array] = {}
    new_residual: dict[str, np.ndarray] = {}
    for name, w in local.items():
        delta = np.asarray(w, np.float32) - np.asarray(received[name], np.float32)
        if name in residual:
            delta = delta + residual[name]
        table = name == TABLE
        chosen = select_rows(delta, rows if table else 1.0)
        arrays[name], sent = encode_delta(delta, chosen, bits if table else mlp_bits)
        new_residual[name] = delta - sent
    return arrays, new_residual
