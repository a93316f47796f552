"""dronecap's HDF5 dataset format: the one module that reads, writes and validates it.

Every stage exchanges data through these files (``frames.h5``, ``posed.h5``, ``dataset.h5``,
``shards/client_K.h5``). Layout of a file (all optional parts may be absent):

    /images        uint8   [N, H, W, C]  C = 1 (gray) or 3 (RGB); one chunk per image, lzf
    /alpha         uint8   [N, H, W]     coverage, 255 = opaque
    /poses         float64 [N, 4, 4]     camera-to-world, OpenCV axes (x right, y down, z fwd)
    /names         str     [N]           source name of each frame (file name or "frame_000123")
    /source_index  int64   [N]           index of the frame in its source (video frame number)
    /timestamps    float64 [N]           seconds from the start of the source
    /split         int8    [N]           0 train, 1 val, 2 test, -1 unassigned
    /near_far      float64 [N, 2]        per-view near/far along the optical axis (scene units)
    /shards/<name> int16   [N]           client of each frame under a named sharding (-1: none)
    /camera_index  int16   [N]           index into attrs `cameras` of every frame (version 3)
    /drone         int16   [N]           the drone (source position 0..D-1) of every frame
    /extra/<name>  any     [...]         stage-specific tables (e.g. ingest's per-frame scores)
    attrs: format="dronecap", format_version, kind, intrinsics (fx, fy, cx, cy),
           distortion model + params, aabb [2, 3], normalization [4, 4], background,
           provenance (JSON: stage, params, input hashes, created),
           cameras (JSON list of Camera dicts, version 3), drone_names (JSON list, version 3)

A camera per frame (format_version 3): ``cameras`` is the table of cameras (one per drone, or
per imported camera) and ``camera_index`` points every frame at its own; ``intrinsics`` is the
camera when the file has exactly one (then equal to ``cameras[0]``) and None when there are
several, so single-camera code keeps working. ``drone`` gives every frame's drone (the
position of its source) and ``drone_names`` a name per drone; ``source_index`` is the frame's
index in its own drone's source. A single flight is a swarm of one: files without these fields
(all of version 1 and 2) read as one camera and drone 0 (:meth:`Dataset.camera_of`,
:meth:`Dataset.drones`).

Intrinsics (:class:`dronecap.camera.Camera`: fx, fy, cx, cy plus a lens-distortion model) are in
pixels of the stored resolution, pixel centres at integer + 0.5
(OpenCV convention: the centre of the top-left pixel is (0.5, 0.5) in continuous coordinates,
so a pixel (u, v) index maps to the ray through (u + 0.5, v + 0.5)).

Integrity (format_version 2, what :func:`write_dataset` writes): every array carries HDF5's
Fletcher-32 checksum filter, the file's metadata (superblock, object headers, attributes) is in
the HDF5 1.10 layout whose blocks carry checksums, and strings are fixed-length (stored inside
the checksummed blocks, not in HDF5's unchecked global heap). A flipped byte anywhere that
matters is therefore a read error, never a different image or pose. Version 1 files (no
checksums) are still read.

A file whose superblock is not the checksummed one (version 1 files, foreign HDF5 files) is
first read in a forked child process (:mod:`dronecap.datasets.probe`): damage that makes HDF5 crash
the process (a segfault) or loop forever becomes a one-line :class:`DatasetError` instead. What
no reader can detect without checksums: a flipped bit in an image, a pose or any other stored
number that leaves the value valid (finite, rigid, in range) reads back as a different dataset.

Validation (:meth:`Dataset.validate`, run on every write and every read; the checks are in
:mod:`dronecap.datasets.checks`) checks the schema,
dtypes and shapes, finite values, rigid camera rotations, the camera (``Camera.problems``), an
AABB with max > min that some camera sees, 0 <= near < far, a background in [0, 1]. Every
failure is a :class:`DatasetError`: one line naming the file, the field and the problem.
"""

from __future__ import annotations

import dataclasses
import io
import json
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from dronecap.camera import Camera
from dronecap.datasets import checks
from dronecap.datasets.checks import KINDS, SPLITS, describe
from dronecap.datasets.probe import checksummed_layout, survives_reading
from dronecap.datasets.safe_paths import hdf5_link_problem
from dronecap.errors import InputError
from dronecap.files import atomic_output, require_free_space

FORMAT = "dronecap"
FORMAT_VERSION = 3  # 3: a camera and a drone per frame; 2: checksums; 1: none (still read)
READ_VERSIONS = (1, 2, 3)
Intrinsics = Camera  # the stored camera: dronecap.camera.Camera (one camera type)
_CAMERA_FIELDS = {f.name for f in dataclasses.fields(Camera)}


class DatasetError(InputError):
    """A dataset file that cannot be used: foreign, newer, truncated or inconsistent."""


@dataclass
class Dataset:
    """An in-memory dronecap dataset. Arrays are indexed by frame along their first axis."""

    images: np.ndarray  # uint8 [N, H, W, C]
    kind: str = "dataset"
    alpha: np.ndarray | None = None  # uint8 [N, H, W]
    poses: np.ndarray | None = None  # float64 [N, 4, 4] camera-to-world, OpenCV axes
    intrinsics: Intrinsics | None = None
    names: list[str] | None = None
    source_index: np.ndarray | None = None  # int64 [N]
    timestamps: np.ndarray | None = None  # float64 [N] seconds
    split: np.ndarray | None = None  # int8 [N]: 0 train, 1 val, 2 test, -1 unassigned
    near_far: np.ndarray | None = None  # float64 [N, 2]
    aabb: np.ndarray | None = None  # float64 [2, 3] (min, max) in scene units
    normalization: np.ndarray | None = None  # float64 [4, 4]: x_scene = M @ x_source
    background: tuple[float, ...] | None = None  # in [0, 1], C values; None: no alpha
    shards: dict[str, np.ndarray] = field(default_factory=dict)  # name -> int16 [N]
    extra: dict[str, np.ndarray] = field(default_factory=dict)
    provenance: dict[str, Any] = field(default_factory=dict)
    attrs: dict[str, Any] = field(default_factory=dict)  # small JSON-able stage metadata
    cameras: list[Camera] | None = None  # the table of cameras (one per drone or import)
    camera_index: np.ndarray | None = None  # int16 [N] index into cameras of every frame
    drone: np.ndarray | None = None  # int16 [N] drone (source position 0..D-1) of every frame
    drone_names: list[str] | None = None  # [D] a name per drone (its source's name)

    @property
    def n(self) -> int:
        """Number of frames."""
        return int(self.images.shape[0])

    @property
    def channels(self) -> int:
        """1 for gray, 3 for RGB."""
        return int(self.images.shape[3])

    @property
    def hw(self) -> tuple[int, int]:
        """(height, width) in pixels."""
        return int(self.images.shape[1]), int(self.images.shape[2])

    def frame_name(self, i: int) -> str:
        """Name of frame ``i``: its source name, or ``frame_000123`` when the file has none."""
        return self.names[i] if self.names is not None else f"frame_{i:06d}"

    def camera_of(self, i: int) -> Camera:
        """The camera of frame ``i``: ``cameras[camera_index[i]]``, or the single camera."""
        if self.cameras is None or self.camera_index is None:
            if self.intrinsics is None:
                raise DatasetError("has no camera intrinsics")
            return self.intrinsics
        return self.cameras[int(self.camera_index[i])]

    def frame_cameras(self) -> list[Camera]:
        """The camera of every frame, [N] (one object shared by the frames of a camera)."""
        return [self.camera_of(i) for i in range(self.n)]

    def drones(self) -> np.ndarray:
        """The drone of every frame, int64 [N] (all 0 for a single flight)."""
        if self.drone is None:
            return np.zeros(self.n, np.int64)
        return np.asarray(self.drone, np.int64)

    def drone_name(self, d: int) -> str:
        """Name of drone ``d``: its source's name, or ``drone_<d>`` when the file has none."""
        return self.drone_names[d] if self.drone_names is not None else f"drone_{d}"

    def set_cameras(self, cameras: list[Camera], camera_index: np.ndarray) -> None:
        """Give frames their own cameras: ``camera_index`` int [N] into ``cameras``; sets
        ``intrinsics`` to the camera when there is exactly one, None otherwise."""
        self.cameras = list(cameras)
        self.camera_index = np.asarray(camera_index, np.int16)
        self.intrinsics = self.cameras[0] if len(self.cameras) == 1 else None

    def indices(self, split: str) -> np.ndarray:
        """Frame indices of a split ("train", "val", "test"), int64 [M]."""
        if self.split is None:
            raise DatasetError(f"has no train/test split (run `dronecap split`) for {split!r}")
        return np.flatnonzero(self.split == SPLITS[split])

    def same_as(self, other: Dataset) -> bool:
        """Every field equal to ``other``'s (arrays exactly, NaN where NaN): a file read back is
        the same data."""
        for f in dataclasses.fields(Dataset):
            x, y = getattr(self, f.name), getattr(other, f.name)
            if isinstance(x, dict) and any(isinstance(v, np.ndarray) for v in x.values()):
                if x.keys() != y.keys() or any(not _same_array(x[k], y[k]) for k in x):
                    return False
            elif isinstance(x, np.ndarray) or isinstance(y, np.ndarray):
                if x is None or y is None or not _same_array(x, y):
                    return False
            elif x != y:
                return False
        return True

    def subset(self, idx: np.ndarray) -> Dataset:
        """A new Dataset holding frames ``idx`` (every per-frame array is sliced)."""
        idx = np.asarray(idx, dtype=np.int64)

        def take(a: np.ndarray | None) -> np.ndarray | None:
            return None if a is None else a[idx]

        return dataclasses.replace(
            self,
            images=self.images[idx],
            alpha=take(self.alpha),
            poses=take(self.poses),
            names=None if self.names is None else [self.names[i] for i in idx],
            source_index=take(self.source_index),
            timestamps=take(self.timestamps),
            split=take(self.split),
            near_far=take(self.near_far),
            shards={k: v[idx] for k, v in self.shards.items()},
            camera_index=take(self.camera_index),
            drone=take(self.drone),
            extra=dict(self.extra),
            provenance=dict(self.provenance),
            attrs=dict(self.attrs),
        )

    def validate(self, path: str | Path | None = None) -> None:
        """Raise :class:`DatasetError` naming ``path`` and the field for the first problem found:
        schema, dtypes, shapes, non-finite values, non-rigid poses, a bad camera, bounds,
        near/far or background out of range."""
        problem = self.problem()
        if problem is not None:
            raise DatasetError(problem, path if path is not None else "<dataset>")

    def problem(self) -> str | None:
        """The first thing wrong with this dataset ("<field>: <problem>"), or None."""
        return checks.problem(self)


def _same_array(a: np.ndarray, b: np.ndarray) -> bool:
    """Same shape and values; NaN equals NaN in float arrays (a score that was not measured)."""
    a, b = np.asarray(a), np.asarray(b)
    return np.array_equal(a, b, equal_nan=a.dtype.kind in "fc" and b.dtype.kind in "fc")


def provenance(stage: str, params: dict[str, Any], inputs: dict[str, str]) -> dict[str, Any]:
    """Provenance record: the stage, its parameters and its inputs' content hashes."""
    return {
        "stage": stage,
        "params": params,
        "inputs": inputs,
        "created": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
    }


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
    if ds.intrinsics is not None:
        _text_attr(f, "intrinsics", json.dumps(dataclasses.asdict(ds.intrinsics)))
    if ds.cameras is not None:
        cams = [dataclasses.asdict(c) for c in ds.cameras]
        _text_attr(f, "cameras", json.dumps(cams, allow_nan=False))
    if ds.drone_names is not None:
        _text_attr(f, "drone_names", json.dumps(list(ds.drone_names)))
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
            f"not a readable HDF5 file (truncated or corrupt?): {_one_line(err)}", path
        ) from None
    try:
        attrs = {k: _as_text(v) for k, v in attrs.items()}
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
                intrinsics=_camera(attrs.get("intrinsics"), path),
                names=None if "names" not in raw else [_as_text(s) for s in raw["names"]],
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
                cameras=_camera_table(attrs.get("cameras"), path),
                camera_index=raw.get("camera_index"),
                drone=raw.get("drone"),
                drone_names=_drone_names(attrs.get("drone_names"), path),
            )
    except DatasetError:
        raise
    except Exception as err:  # h5py's errors for damaged data are of many types  # noqa: BLE001
        raise DatasetError(f"{where}: damaged or truncated: {_one_line(err)}", path) from None
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
        text = _one_line(err)
        if checksums and ("filter" in text.lower() or "checksum" in text.lower()):
            damaged = f"{name}: checksum mismatch (the stored data is damaged)"
            raise DatasetError(damaged, path) from None
        raise


def _as_text(value: object) -> Any:
    """bytes -> str (UTF-8); anything else unchanged."""
    if isinstance(value, bytes | np.bytes_):
        return bytes(value).decode()
    return value


def _camera(value: object, path: Path) -> Camera | None:
    """The ``intrinsics`` attribute (JSON object of Camera's fields) -> Camera."""
    if value is None:
        return None
    return _camera_from(_json_value(value, "intrinsics", path), "intrinsics", path)


def _camera_table(value: object, path: Path) -> list[Camera] | None:
    """The ``cameras`` attribute (JSON list of Camera objects) -> [Camera] (None when absent)."""
    if value is None:
        return None
    items = _json_value(value, "cameras", path)
    if not isinstance(items, list) or not items:
        raise DatasetError("cameras: must be a non-empty JSON list of cameras", path)
    return [_camera_from(d, f"cameras[{i}]", path) for i, d in enumerate(items)]


def _drone_names(value: object, path: Path) -> list[str] | None:
    """The ``drone_names`` attribute (JSON list of strings) -> [str] (None when absent)."""
    if value is None:
        return None
    names = _json_value(value, "drone_names", path)
    if not isinstance(names, list) or not all(isinstance(s, str) for s in names):
        raise DatasetError("drone_names: must be a JSON list of strings", path)
    return names


def _camera_from(d: object, value: object, path: Path) -> Camera:
    """A JSON object of Camera's fields -> Camera; ``value`` names it in errors."""
    if not isinstance(d, dict) or set(d) != _CAMERA_FIELDS:
        raise DatasetError(f"{value}: must be a JSON object of {sorted(_CAMERA_FIELDS)}", path)
    numbers = [d[k] for k in ("fx", "fy", "cx", "cy")]
    dist = d["distortion"]
    ok = (
        all(isinstance(x, int | float) and not isinstance(x, bool) for x in numbers)
        and all(isinstance(d[k], int) and not isinstance(d[k], bool) for k in ("width", "height"))
        and isinstance(d["model"], str)
        and isinstance(dist, list)
        and all(isinstance(x, int | float) and not isinstance(x, bool) for x in dist)
    )
    if not ok:
        raise DatasetError(f"{value}: fields of the wrong type in {d!r:.120}", path)
    return Camera(
        *map(float, numbers), d["width"], d["height"], d["model"], tuple(map(float, dist))
    )


def _json_value(value: object, name: str, path: Path) -> Any:
    if not isinstance(value, str):
        raise DatasetError(f"{name}: must be a JSON string, found {describe(value)}", path)
    try:
        return json.loads(value)
    except ValueError as err:
        raise DatasetError(f"{name}: not valid JSON ({err})", path) from None


def _json_object(attrs: dict[str, Any], name: str, path: Path) -> dict[str, Any]:
    d = _json_value(attrs.get(name, "{}"), name, path)
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
    a = _float_attr(attrs, "background", path)
    return None if a is None else tuple(float(x) for x in np.atleast_1d(a).ravel())


def _decode(a: np.ndarray) -> np.ndarray:
    if a.dtype.kind in "OS":
        return np.array([s.decode() if isinstance(s, bytes) else s for s in a])
    return a


def _one_line(err: BaseException) -> str:
    """An exception as one short line (h5py's messages can span several)."""
    text = " ".join(str(err).split()) or type(err).__name__
    return text[:200]
