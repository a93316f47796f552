"""A dataset file's header: the format name, the version written and the versions still read.

Version 3 adds a camera and a drone per frame, version 2 the checksums; version 1 files (no
checksums, one camera) are still read: the fields they lack read as absent, so a version 1 or 2
file is one camera and drone 0 (:meth:`~dronecap.datasets.dataset.Dataset.camera_of`). Also the
attribute helpers the reader shares: text, JSON strings, one-line HDF5 errors.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from dronecap.datasets.checks import describe
from dronecap.datasets.dataset import DatasetError

FORMAT = "dronecap"
FORMAT_VERSION = 3  # 3: a camera and a drone per frame; 2: checksums; 1: none (still read)
READ_VERSIONS = (1, 2, 3)


def read_header(path: str | Path) -> dict[str, Any]:
    """Check a file is a dronecap dataset this version can read; return its top-level attrs
    (``format_version`` as an int, strings decoded)."""
    path = Path(path)
    if not path.exists():
        raise DatasetError("no such file", path)
    if path.is_dir():
        raise DatasetError("is a folder, expected a dataset file", path)
    if not path.is_file():  # a FIFO or device would block or stream forever
        raise DatasetError("is not a regular file", path)
    try:
        with h5py.File(path, "r") as f:
            attrs = dict(f.attrs)
    except Exception as err:  # h5py raises many types for damaged headers  # noqa: BLE001
        raise DatasetError(
            f"not a readable HDF5 file (truncated or corrupt?): {one_line(err)}", path
        ) from None
    try:
        attrs = {k: as_text(v) for k, v in attrs.items()}
    except UnicodeDecodeError as err:
        raise DatasetError(f"attributes: text that is not UTF-8 ({err})", path) from None
    fmt = attrs.get("format")
    if fmt != FORMAT:
        raise DatasetError(f"not a dronecap dataset (format attribute {fmt!r})", path)
    version = attrs.get("format_version")
    if isinstance(version, np.ndarray) and version.shape == ():
        version = version[()]
    if isinstance(version, bool | np.bool_) or not isinstance(version, int | np.integer):
        raise DatasetError(f"format_version: must be an integer, found {version!r}", path)
    version = int(version)
    if version > FORMAT_VERSION:
        raise DatasetError(
            f"format_version {version} is newer than this dronecap reads ({FORMAT_VERSION});"
            " upgrade dronecap",
            path,
        )
    if version not in READ_VERSIONS:
        raise DatasetError(f"invalid format_version {version}", path)
    attrs["format_version"] = version
    return attrs


def as_text(value: object) -> Any:
    """bytes -> str (UTF-8); anything else unchanged."""
    if isinstance(value, bytes | np.bytes_):
        return bytes(value).decode()
    return value


def json_attr(value: object, name: str, path: Path) -> Any:
    """A JSON string attribute ``name`` -> its value (DatasetError when it is not one)."""
    if not isinstance(value, str):
        raise DatasetError(f"{name}: must be a JSON string, found {describe(value)}", path)
    try:
        return json.loads(value)
    except ValueError as err:
        raise DatasetError(f"{name}: not valid JSON ({err})", path) from None


def one_line(err: BaseException) -> str:
    """An exception as one short line (h5py's messages can span several)."""
    text = " ".join(str(err).split()) or type(err).__name__
    return text[:200]
