"""The camera table and drone names as stored in a file's attributes (JSON strings).

``intrinsics`` is one camera, ``cameras`` the table of a file with a camera per frame and
``drone_names`` a name per drone (:mod:`dronecap.datasets.format`). :func:`camera_attrs` gives
the attributes a dataset stores; :func:`read_camera`, :func:`read_camera_table` and
:func:`read_drone_names` read them back, refusing anything that is not exactly a camera.
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

from dronecap.camera import Camera
from dronecap.datasets.dataset import Dataset, DatasetError
from dronecap.datasets.header import json_attr

_CAMERA_FIELDS = {f.name for f in dataclasses.fields(Camera)}


def read_camera(value: object, path: Path) -> Camera | None:
    """The ``intrinsics`` attribute (JSON object of Camera's fields) -> Camera."""
    if value is None:
        return None
    return _camera_from(json_attr(value, "intrinsics", path), "intrinsics", path)


def read_camera_table(value: object, path: Path) -> list[Camera] | None:
    """The ``cameras`` attribute (JSON list of Camera objects) -> [Camera] (None when absent)."""
    if value is None:
        return None
    items = json_attr(value, "cameras", path)
    if not isinstance(items, list) or not items:
        raise DatasetError("cameras: must be a non-empty JSON list of cameras", path)
    return [_camera_from(d, f"cameras[{i}]", path) for i, d in enumerate(items)]


def read_drone_names(value: object, path: Path) -> list[str] | None:
    """The ``drone_names`` attribute (JSON list of strings) -> [str] (None when absent)."""
    if value is None:
        return None
    names = json_attr(value, "drone_names", path)
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


def camera_attrs(ds: Dataset) -> dict[str, str]:
    """The JSON text attributes of ``ds``'s cameras and drone names (the ones it has)."""
    out = {}
    if ds.intrinsics is not None:
        out["intrinsics"] = json.dumps(dataclasses.asdict(ds.intrinsics))
    if ds.cameras is not None:
        cams = [dataclasses.asdict(c) for c in ds.cameras]
        out["cameras"] = json.dumps(cams, allow_nan=False)
    if ds.drone_names is not None:
        out["drone_names"] = json.dumps(list(ds.drone_names))
    return out
