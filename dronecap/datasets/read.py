"""Reading a dataset file: :func:`open_dataset` (whole file, validated, damage as one line).

A file without the checksummed superblock (version 1, foreign HDF5) is first read in a forked
child (:mod:`dronecap.datasets.probe`), so damage that crashes HDF5 is a :class:`DatasetError`.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import h5py
import numpy as np

from dronecap.datasets.camera_attrs import read_camera, read_camera_table, read_drone_names
from dronecap.datasets.checks import KINDS, describe
from dronecap.datasets.dataset import Dataset, DatasetError
from dronecap.datasets.header import as_text, json_attr, one_line, read_header
from dronecap.datasets.probe import checksummed_layout, survives_reading
from dronecap.datasets.safe_paths import hdf5_link_problem


def open_dataset(path: str | Path, kinds: tuple[str, ...] | None = None) -> Dataset:
    """Read a whole dataset file into memory and validate it.

    Args:
        path: the ``.h5`` file.
        kinds: if given, the file's ``kind`` must be one of these (e.g. ``("dataset", "shard")``).

    Raises:
        DatasetError: one line naming the file, the field and what is wrong (a checksum
            mismatch included).
    """
    path = Path(path)
    if path.is_file() and not checksummed_layout(path):
        survives_reading(path, lambda p: _read_dataset(p, None), DatasetError)
    return _read_dataset(path, kinds)


def _read_dataset(path: Path, kinds: tuple[str, ...] | None) -> Dataset:
    """:func:`open_dataset` without the probe: may crash the process on a damaged v1 file."""
    attrs = read_header(path)
    kind = attrs.get("kind")
    if not isinstance(kind, str) or kind not in KINDS:
        raise DatasetError(f"kind: unknown kind {kind!r}, expected one of {list(KINDS)}", path)
    if kinds is not None and kind not in kinds:
        raise DatasetError(f"is a {kind!r} file, expected one of {list(kinds)}", path)
    checksums = attrs["format_version"] >= 2
    where = "file structure"
    try:
        with h5py.File(path, "r") as f:
            if outside := hdf5_link_problem(f):  # a dataset file is read alone (safe_paths.py)
                raise DatasetError(outside, path)
            if "images" not in f or not isinstance(f["images"], h5py.Dataset):
                raise DatasetError("images: missing required dataset", path)
            names = ["images", "alpha", "poses", "names", "source_index", "timestamps", "split"]
            names += ["near_far", "camera_index", "drone"]
            for group in ("shards", "extra"):
                if group in f:
                    if not isinstance(f[group], h5py.Group):
                        raise DatasetError(f"{group}: expected a group of arrays", path)
                    names += [f"{group}/{k}" for k in f[group]]
            raw: dict[str, np.ndarray] = {}
            for where in names:
                if where in f:
                    raw[where] = _read_array(f, where, checksums, path)
            where = "attributes"
            ds = Dataset(
                images=raw["images"],
                kind=kind,
                alpha=raw.get("alpha"),
                poses=raw.get("poses"),
                intrinsics=read_camera(attrs.get("intrinsics"), path),
                names=None if "names" not in raw else [as_text(s) for s in raw["names"]],
                source_index=raw.get("source_index"),
                timestamps=raw.get("timestamps"),
                split=raw.get("split"),
                near_far=raw.get("near_far"),
                aabb=_float_attr(attrs, "aabb", path),
                normalization=_float_attr(attrs, "normalization", path),
                background=_background(attrs, path),
                shards={k[7:]: v for k, v in raw.items() if k.startswith("shards/")},
                extra={k[6:]: _decode(v) for k, v in raw.items() if k.startswith("extra/")},
                provenance=_json_object(attrs, "provenance", path),
                attrs=_json_object(attrs, "stage_attrs", path),
                cameras=read_camera_table(attrs.get("cameras"), path),
                camera_index=raw.get("camera_index"),
                drone=raw.get("drone"),
                drone_names=read_drone_names(attrs.get("drone_names"), path),
            )
    except DatasetError:
        raise
    except Exception as err:  # h5py's errors for damaged data are of many types  # noqa: BLE001
        raise DatasetError(f"{where}: damaged or truncated: {one_line(err)}", path) from None
    ds.validate(path)
    return ds


def _read_array(f: h5py.File, name: str, checksums: bool, path: Path) -> np.ndarray:
    """Read one stored array, refusing missing chunks and (version 2) a missing checksum."""
    d = f[name]
    if not isinstance(d, h5py.Dataset):
        raise DatasetError(f"{name}: expected an array, found a group", path)
    if d.size and checksums and not d.fletcher32:
        raise DatasetError(f"{name}: stored without its checksum", path)
    if d.size and d.chunks is not None:
        expected = int(np.prod([-(-s // c) for s, c in zip(d.shape, d.chunks, strict=True)]))
        stored = d.id.get_num_chunks()
        if stored != expected:
            raise DatasetError(f"{name}: {expected - stored} of {expected} chunks missing", path)
    try:
        return d[()]
    except OSError as err:
        text = one_line(err)
        if checksums and ("filter" in text.lower() or "checksum" in text.lower()):
            damaged = f"{name}: checksum mismatch (the stored data is damaged)"
            raise DatasetError(damaged, path) from None
        raise


def _json_object(attrs: dict[str, Any], name: str, path: Path) -> dict[str, Any]:
    """A JSON object attribute (``provenance``, ``stage_attrs``; ``{}`` when absent)."""
    d = json_attr(attrs.get(name, "{}"), name, path)
    if not isinstance(d, dict):
        raise DatasetError(f"{name}: must be a JSON object, found {type(d).__name__}", path)
    return d


def _float_attr(attrs: dict[str, Any], name: str, path: Path) -> np.ndarray | None:
    """A numeric array attribute as float64 (None when absent)."""
    value = attrs.get(name)
    if value is None:
        return None
    a = np.asarray(value)
    if a.dtype.kind not in "fiu":
        raise DatasetError(f"{name}: must be numbers, found {describe(value)}", path)
    return a.astype(np.float64)


def _background(attrs: dict[str, Any], path: Path) -> tuple[float, ...] | None:
    """The ``background`` attribute as a tuple of floats (None when absent)."""
    a = _float_attr(attrs, "background", path)
    return None if a is None else tuple(float(x) for x in np.atleast_1d(a).ravel())


def _decode(a: np.ndarray) -> np.ndarray:
    """An ``extra`` table of byte strings -> str array; other arrays unchanged."""
    if a.dtype.kind in "OS":
        return np.array([s.decode() if isinstance(s, bytes) else s for s in a])
    return a
