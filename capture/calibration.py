"""Source camera intrinsics from the command line or a calibration JSON file.

Accepted forms (all in pixels of the source frames, pixel centres at integer + 0.5):

- ``"fx,fy,cx,cy"`` on the command line (the source frame size is taken from the video);
- a JSON file with ``fx, fy, cx, cy`` and optionally ``width, height`` at the top level or under
  ``"intrinsics"`` (the simulator's ``flight.json`` is such a file);
- a JSON file with a 3x3 ``"K"`` or ``"camera_matrix"`` (OpenCV calibration style) and optionally
  ``"width"/"height"`` or ``"image_width"/"image_height"``.

When the calibration's size differs from the video's but has the same aspect ratio, the
intrinsics are scaled to the video (a camera recorded at half its calibrated resolution).
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from dronecap.capture.framing import CameraModel, parse_numbers
from dronecap.errors import InputError


def load_intrinsics(spec: str, source_size: tuple[int, int]) -> CameraModel:
    """Parse ``spec`` ("fx,fy,cx,cy" or a JSON path) into intrinsics for ``source_size`` (w, h).

    Raises:
        InputError: unreadable file, missing keys, non-positive focal length, or a calibration
            whose aspect ratio does not match the frames.
    """
    path = Path(spec)
    if path.suffix.lower() == ".json" or path.exists():
        cam = _from_json(path)
    else:
        try:
            fx, fy, cx, cy = parse_numbers(
                spec, 4, float, "--intrinsics must be 'fx,fy,cx,cy' or a calibration JSON file"
            )
        except ValueError as err:
            raise InputError(str(err)) from None
        cam = (fx, fy, cx, cy, None, None)
    fx, fy, cx, cy, w, h = cam
    if not (fx > 0 and fy > 0):
        raise InputError(f"focal lengths must be positive, found fx={fx}, fy={fy}", spec)
    sw, sh = source_size
    model = CameraModel(fx, fy, cx, cy, int(w or sw), int(h or sh))
    if (model.width, model.height) == (sw, sh):
        return model
    if abs(model.width * sh - model.height * sw) > max(sw, sh):
        raise InputError(
            f"calibration is for {model.width}x{model.height} frames but the source is {sw}x{sh}"
            " (different aspect ratio)",
            spec,
        )
    return model.scaled_to(sw, sh)


def _from_json(path: Path) -> tuple[float, float, float, float, int | None, int | None]:
    if not path.exists():
        raise InputError("calibration file not found", path)
    try:
        doc: Any = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as err:
        raise InputError(f"not a readable calibration JSON: {err}", path) from None
    if not isinstance(doc, dict):
        raise InputError("calibration JSON must be an object", path)
    d = doc.get("intrinsics", doc)
    if not isinstance(d, dict):
        raise InputError("'intrinsics' must be an object with fx, fy, cx, cy", path)
    try:
        if all(k in d for k in ("fx", "fy", "cx", "cy")):
            fx, fy, cx, cy = (float(d[k]) for k in ("fx", "fy", "cx", "cy"))
        else:
            k = d.get("K", d.get("camera_matrix"))
            if k is None:
                raise KeyError("fx, fy, cx, cy (or a 3x3 K / camera_matrix)")
            fx, fy, cx, cy = float(k[0][0]), float(k[1][1]), float(k[0][2]), float(k[1][2])
        w = d.get("width", d.get("image_width"))
        h = d.get("height", d.get("image_height"))
        return fx, fy, cx, cy, None if w is None else int(w), None if h is None else int(h)
    except (KeyError, IndexError, TypeError, ValueError) as err:
        raise InputError(f"calibration JSON lacks usable intrinsics: {err}", path) from None
