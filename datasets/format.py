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
    /extra/<name>  any     [...]         stage-specific tables (e.g. ingest's per-frame scores)
    attrs: format="dronecap", format_version, kind, intrinsics (fx, fy, cx, cy),
           distortion model + params, aabb [2, 3], normalization [4, 4], background,
           provenance (JSON: stage, params, input hashes, created)

Intrinsics (:class:`dronecap.camera.Camera`: fx, fy, cx, cy plus a lens-distortion model) are in
pixels of the stored resolution, pixel centres at integer + 0.5
(OpenCV convention: the centre of the top-left pixel is (0.5, 0.5) in continuous coordinates,
so a pixel (u, v) index maps to the ray through (u + 0.5, v + 0.5)).
"""

from __future__ import annotations

import dataclasses
import json
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from dronecap.camera import Camera
from dronecap.errors import InputError
from dronecap.files import atomic_output

FORMAT = "dronecap"
FORMAT_VERSION = 1
KINDS = ("frames", "posed", "dataset", "shard")
SPLITS = {"train": 0, "val": 1, "test": 2}
Intrinsics = Camera  # the stored camera: dronecap.camera.Camera (one camera type)


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

    def indices(self, split: str) -> np.ndarray:
        """Frame indices of a split ("train", "val", "test"), int64 [M]."""
        if self.split is None:
            raise DatasetError(f"has no train/test split (run `dronecap split`) for {split!r}")
        return np.flatnonzero(self.split == SPLITS[split])

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
            extra=dict(self.extra),
            provenance=dict(self.provenance),
            attrs=dict(self.attrs),
        )

    def validate(self, path: str | Path | None = None) -> None:
        """Raise :class:`DatasetError` naming ``path`` when shapes or dtypes disagree."""
        where = path if path is not None else "<dataset>"

        def fail(msg: str) -> None:
            raise DatasetError(msg, where)

        im = self.images
        if im.dtype != np.uint8 or im.ndim != 4 or im.shape[3] not in (1, 3):
            fail(f"images must be uint8 [N,H,W,1|3], found {im.dtype} {list(im.shape)}")
        if self.kind not in KINDS:
            fail(f"unknown kind {self.kind!r}, expected one of {KINDS}")
        n, h, w = im.shape[:3]
        per_frame = {
            "alpha": (self.alpha, (n, h, w)),
            "poses": (self.poses, (n, 4, 4)),
            "source_index": (self.source_index, (n,)),
            "timestamps": (self.timestamps, (n,)),
            "split": (self.split, (n,)),
            "near_far": (self.near_far, (n, 2)),
        }
        for name, (arr, shape) in per_frame.items():
            if arr is not None and tuple(arr.shape) != shape:
                fail(f"{name} has shape {list(arr.shape)}, expected {list(shape)}")
        if self.alpha is not None and self.alpha.dtype != np.uint8:
            fail(f"alpha must be uint8, found {self.alpha.dtype}")
        if self.split is not None and not np.isin(self.split, [-1, *SPLITS.values()]).all():
            fail(f"split values must be -1, 0, 1 or 2, found {sorted(set(self.split.tolist()))}")
        for name, arr in self.shards.items():
            if tuple(arr.shape) != (n,):
                fail(f"shards/{name} has shape {list(arr.shape)}, expected [{n}]")
        if self.names is not None and len(self.names) != n:
            fail(f"names has {len(self.names)} entries, expected {n}")
        if self.poses is not None and not np.isfinite(self.poses).all():
            fail("poses contain non-finite values")
        if self.aabb is not None:
            a = np.asarray(self.aabb)
            if a.shape != (2, 3) or not np.all(a[1] > a[0]):
                fail(f"aabb must be [[min xyz], [max xyz]] with max > min, found {a.tolist()}")
        if self.intrinsics is not None:
            k = self.intrinsics
            if (k.width, k.height) != (w, h):
                fail(f"intrinsics are for {k.width}x{k.height} but images are {w}x{h}")
            for problem in k.problems():
                fail(problem)
        if self.background is not None and len(self.background) != im.shape[3]:
            fail(f"background has {len(self.background)} values for {im.shape[3]} channels")


def provenance(stage: str, params: dict[str, Any], inputs: dict[str, str]) -> dict[str, Any]:
    """Provenance record: the stage, its parameters and its inputs' content hashes."""
    return {
        "stage": stage,
        "params": params,
        "inputs": inputs,
        "created": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
    }


def write_dataset(path: str | Path, ds: Dataset) -> Path:
    """Validate ``ds`` and write it atomically to ``path`` (temporary name, then rename)."""
    path = Path(path)
    ds.validate(path)
    with atomic_output(path) as tmp, h5py.File(tmp, "w") as f:
        n, h, w, c = ds.images.shape
        f.attrs["format"] = FORMAT
        f.attrs["format_version"] = FORMAT_VERSION
        f.attrs["kind"] = ds.kind
        f.create_dataset(
            "images", data=ds.images, chunks=(1, h, w, c) if n else None, compression="lzf"
        )
        if ds.alpha is not None:
            f.create_dataset(
                "alpha", data=ds.alpha, chunks=(1, h, w) if n else None, compression="lzf"
            )
        arrays = {
            "poses": (ds.poses, np.float64),
            "source_index": (ds.source_index, np.int64),
            "timestamps": (ds.timestamps, np.float64),
            "split": (ds.split, np.int8),
            "near_far": (ds.near_far, np.float64),
        }
        for name, (arr, dtype) in arrays.items():
            if arr is not None:
                f.create_dataset(name, data=np.asarray(arr, dtype=dtype))
        if ds.names is not None:
            f.create_dataset("names", data=np.array(ds.names, dtype=h5py.string_dtype()))
        for name, arr in ds.shards.items():
            f.create_dataset(f"shards/{name}", data=np.asarray(arr, dtype=np.int16))
        for name, arr in ds.extra.items():
            arr = np.asarray(arr)
            if arr.dtype.kind == "U":
                arr = arr.astype(h5py.string_dtype())
            f.create_dataset(f"extra/{name}", data=arr)
        if ds.intrinsics is not None:
            f.attrs["intrinsics"] = json.dumps(dataclasses.asdict(ds.intrinsics))
        if ds.aabb is not None:
            f.attrs["aabb"] = np.asarray(ds.aabb, dtype=np.float64)
        if ds.normalization is not None:
            f.attrs["normalization"] = np.asarray(ds.normalization, dtype=np.float64)
        if ds.background is not None:
            f.attrs["background"] = np.asarray(ds.background, dtype=np.float64)
        f.attrs["provenance"] = json.dumps(ds.provenance)
        f.attrs["stage_attrs"] = json.dumps(ds.attrs)
    return path


def read_header(path: str | Path) -> dict[str, Any]:
    """Check a file is a dronecap dataset this version can read; return its top-level attrs."""
    path = Path(path)
    if not path.exists():
        raise DatasetError("no such file", path)
    try:
        with h5py.File(path, "r") as f:
            attrs = dict(f.attrs)
    except OSError as err:
        raise DatasetError(
            f"not a readable HDF5 file (truncated or corrupt?): {err}", path
        ) from None
    fmt = attrs.get("format")
    if fmt != FORMAT:
        raise DatasetError(f"not a dronecap dataset (format attribute {fmt!r})", path)
    version = int(attrs.get("format_version", -1))
    if version > FORMAT_VERSION:
        raise DatasetError(
            f"format_version {version} is newer than this dronecap reads ({FORMAT_VERSION});"
            " upgrade dronecap",
            path,
        )
    if version < 1:
        raise DatasetError(f"invalid format_version {version}", path)
    return attrs


def open_dataset(path: str | Path, kinds: tuple[str, ...] | None = None) -> Dataset:
    """Read a whole dataset file into memory and validate it.

    Args:
        path: the ``.h5`` file.
        kinds: if given, the file's ``kind`` must be one of these (e.g. ``("dataset", "shard")``).

    Raises:
        DatasetError: one line naming the file and what is wrong.
    """
    path = Path(path)
    attrs = read_header(path)
    kind = str(attrs.get("kind", ""))
    if kinds is not None and kind not in kinds:
        raise DatasetError(f"is a {kind!r} file, expected one of {list(kinds)}", path)
    try:
        with h5py.File(path, "r") as f:
            if "images" not in f:
                raise DatasetError("missing required dataset 'images'", path)

            def opt(name: str) -> np.ndarray | None:
                return f[name][()] if name in f else None

            intr = attrs.get("intrinsics")
            k = None
            if intr is not None:
                d = json.loads(intr)
                d["distortion"] = tuple(d.get("distortion", ()))
                k = Intrinsics(**d)
            bg = attrs.get("background")
            ds = Dataset(
                images=f["images"][()],
                kind=kind,
                alpha=opt("alpha"),
                poses=opt("poses"),
                intrinsics=k,
                names=[s.decode() for s in f["names"][()]] if "names" in f else None,
                source_index=opt("source_index"),
                timestamps=opt("timestamps"),
                split=opt("split"),
                near_far=opt("near_far"),
                aabb=attrs.get("aabb"),
                normalization=attrs.get("normalization"),
                background=None if bg is None else tuple(float(x) for x in np.atleast_1d(bg)),
                shards={k2: v[()] for k2, v in f["shards"].items()} if "shards" in f else {},
                extra={k2: _decode(v[()]) for k2, v in f["extra"].items()} if "extra" in f else {},
                provenance=json.loads(attrs.get("provenance", "{}")),
                attrs=json.loads(attrs.get("stage_attrs", "{}")),
            )
    except DatasetError:
        raise
    except (OSError, KeyError, ValueError, TypeError) as err:
        raise DatasetError(f"damaged or truncated dataset: {err}", path) from None
    ds.validate(path)
    return ds


def _decode(a: np.ndarray) -> np.ndarray:
    if a.dtype.kind == "O":
        return np.array([s.decode() if isinstance(s, bytes) else s for s in a])
    return a
