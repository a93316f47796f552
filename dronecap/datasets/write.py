"""Writing a dataset file: :func:`write_dataset` (validated, checksummed, atomic).

Every array carries HDF5's Fletcher-32 checksum, metadata is in the checksummed HDF5 1.10
layout and strings are fixed-length (layout and integrity: :mod:`dronecap.datasets.format`).
"""

from __future__ import annotations

import io
import json
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from dronecap.datasets.camera_attrs import camera_attrs
from dronecap.datasets.dataset import Dataset
from dronecap.datasets.header import FORMAT, FORMAT_VERSION
from dronecap.files import atomic_output, require_free_space


def write_dataset(path: str | Path, ds: Dataset) -> Path:
    """Validate ``ds`` and write it atomically to ``path`` (temporary name, then rename).

    The HDF5 file is built in memory and written with plain file I/O after a free-space check,
    so a full disk is a one-line :class:`~dronecap.errors.OutputError` (HDF5 itself crashes the
    process when its writes fail) and an existing ``path`` is kept.
    """
    path = Path(path)
    ds.validate(path)
    buf = io.BytesIO()
    with h5py.File(buf, "w", libver=("v110", "latest")) as f:
        _fill(f, ds)
    data = buf.getbuffer()
    require_free_space(path, len(data))
    with atomic_output(path) as tmp, open(tmp, "wb") as out:
        out.write(data)
    return path


def _fill(f: h5py.File, ds: Dataset) -> None:
    """Store every field of ``ds`` in the open file ``f`` (layout: module docstring)."""
    n, h, w, c = ds.images.shape
    _text_attr(f, "format", FORMAT)
    f.attrs["format_version"] = np.int64(FORMAT_VERSION)
    _text_attr(f, "kind", ds.kind)
    _array(f, "images", ds.images, chunks=(1, h, w, c), lzf=True)
    if ds.alpha is not None:
        _array(f, "alpha", ds.alpha, chunks=(1, h, w), lzf=True)
    arrays = {
        "poses": (ds.poses, np.float64),
        "source_index": (ds.source_index, np.int64),
        "timestamps": (ds.timestamps, np.float64),
        "split": (ds.split, np.int8),
        "near_far": (ds.near_far, np.float64),
        "camera_index": (ds.camera_index, np.int16),
        "drone": (ds.drone, np.int16),
    }
    for name, (arr, dtype) in arrays.items():
        if arr is not None:
            _array(f, name, np.asarray(arr, dtype=dtype))
    if ds.names is not None:
        _array(f, "names", _fixed_strings(ds.names))
    for name, arr in ds.shards.items():
        _array(f, f"shards/{name}", np.asarray(arr, dtype=np.int16))
    for name, arr in ds.extra.items():
        arr = np.asarray(arr)
        _array(f, f"extra/{name}", _fixed_strings(arr) if arr.dtype.kind == "U" else arr)
    for name, text in camera_attrs(ds).items():
        _text_attr(f, name, text)
    if ds.aabb is not None:
        f.attrs["aabb"] = np.asarray(ds.aabb, dtype=np.float64)
    if ds.normalization is not None:
        f.attrs["normalization"] = np.asarray(ds.normalization, dtype=np.float64)
    if ds.background is not None:
        f.attrs["background"] = np.asarray(ds.background, dtype=np.float64)
    _text_attr(f, "provenance", json.dumps(ds.provenance, allow_nan=False))
    _text_attr(f, "stage_attrs", json.dumps(ds.attrs, allow_nan=False))


def _array(
    f: h5py.File, name: str, data: np.ndarray, chunks: tuple[int, ...] | None = None, lzf=False
) -> None:
    """Store ``data`` with a Fletcher-32 checksum (empty arrays have nothing to check)."""
    if data.size == 0:
        f.create_dataset(name, data=data)
        return
    f.create_dataset(
        name,
        data=data,
        chunks=chunks or data.shape,
        compression="lzf" if lzf else None,
        fletcher32=True,
    )


def _text_attr(f: h5py.File, name: str, text: str) -> None:
    """A fixed-length UTF-8 string attribute (kept in the checksummed object header)."""
    f.attrs.create(name, np.bytes_(text.encode()))


def _fixed_strings(items: Any) -> np.ndarray:
    """Strings -> fixed-length UTF-8 bytes [N] (h5py marks them as such)."""
    raw = [str(s).encode() for s in items]
    width = max([len(b) for b in raw] + [1])
    return np.array(raw, dtype=h5py.string_dtype("utf-8", width))
