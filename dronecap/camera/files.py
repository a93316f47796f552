"""Calibration files: the one loader for every form of known intrinsics, and the JSON writer.

Accepted forms (pixels of the calibrated frames, OpenCV's distortion order
``k1, k2, p1, p2[, k3[, k4, k5, k6]]``; fisheye ``k1, k2, k3, k4``):

- ``"fx,fy,cx,cy"`` (the frame size is the source's);
- the calibration JSON of ``dronecap calibrate``: ``K`` (3x3), ``distortion``, ``model``
  (``"pinhole"`` | ``"fisheye"``), ``width``, ``height`` (see :func:`calibration_record`);
- the simulator's ``flight.json``: the same keys as ``fx, fy, cx, cy`` under ``"intrinsics"``;
- other JSON calibrations: ``fx, fy, cx, cy`` or a 3x3 ``K`` / ``camera_matrix``, with
  ``distortion`` / ``dist`` / ``distortion_coefficients`` and ``width``/``height`` or
  ``image_width``/``image_height`` (or ``size: [w, h]``), at the top level or under
  ``"intrinsics"``;
- OpenCV ``FileStorage`` YAML or XML (``.yml``, ``.yaml``, ``.xml``): ``camera_matrix``,
  ``distortion_coefficients``, ``image_width``, ``image_height`` (what OpenCV's calibration
  samples write); a fisheye one says so with ``fisheye_model: 1`` or ``model: fisheye``. ROS
  ``camera_info`` YAML (plain ``{rows, cols, data}`` matrices, ``distortion_model``
  ``plumb_bob`` | ``rational_polynomial`` | ``equidistant``) is read the same way.

Pixel convention: dronecap (like COLMAP) puts the centre of pixel (u, v) at (u + 0.5, v + 0.5);
OpenCV puts it at (u, v). ``fx, fy, cx, cy`` keys are taken as dronecap's; a matrix (``K`` /
``camera_matrix``, JSON or YAML/XML) as OpenCV's, so 0.5 px is added to its cx, cy -- unless the
file says ``"pixel_center_offset": 0.5`` (what :func:`calibration_record` writes).

Distortion is never dropped: a file with distortion gives a :class:`Camera` with it, or an
:class:`InputError` when it cannot be represented. A calibration of another size with the same
aspect ratio is scaled to the source (a camera recorded at half its calibrated resolution);
another aspect ratio is an error.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import numpy as np

from dronecap.camera.model import Camera
from dronecap.errors import InputError

OPENCV_STORAGE_SUFFIXES = (".yml", ".yaml", ".xml")
ASPECT_TOLERANCE_PX = 1.0  # sizes of the same aspect may differ by this much after rounding
MODELS = ("pinhole", "fisheye")  # "model" of a calibration JSON (OpenCV's two lens families)
ROS_MODELS = {"plumb_bob": "pinhole", "rational_polynomial": "pinhole", "equidistant": "fisheye"}
DRONECAP_OFFSET = 0.5  # dronecap's pixel (u, v) has its centre at (u + 0.5, v + 0.5)
OPENCV_OFFSET = 0.0  # OpenCV's at (u, v)


def load_camera(spec: str, source_size: tuple[int, int]) -> tuple[Camera, str]:
    """The camera of frames of ``source_size`` (w, h) from ``spec``, and where it came from.

    Returns:
        (camera sized to the source, origin) with origin ``"flight.json"`` for a simulator's
        ground truth and ``"calibration"`` for everything else (a file or ``fx,fy,cx,cy``).

    Raises:
        InputError: unreadable or incomplete file, bad values, or a different aspect ratio.
    """
    path = Path(spec)
    if path.suffix.lower() in (".json", *OPENCV_STORAGE_SUFFIXES) or path.exists():
        cam, origin = read_camera(path, source_size)
    else:
        parts = spec.split(",")
        try:
            fx, fy, cx, cy = (float(v) for v in parts)
        except ValueError:
            raise InputError(
                f"intrinsics must be 'fx,fy,cx,cy' or a calibration file, got {spec!r}"
            ) from None
        cam, origin = Camera(fx, fy, cx, cy, *source_size), "calibration"
    problems = cam.problems()
    if problems:
        raise InputError(f"unusable camera: {problems[0]}", spec)
    return fit_to_source(cam, source_size, spec), origin


def fit_to_source(cam: Camera, source_size: tuple[int, int], where: str | Path) -> Camera:
    """``cam`` scaled to ``source_size`` (w, h) when only the resolution differs.

    Raises:
        InputError: the calibration's aspect ratio differs from the source's.
    """
    sw, sh = source_size
    if (cam.width, cam.height) == (sw, sh):
        return cam
    if abs(cam.width * sh - cam.height * sw) > ASPECT_TOLERANCE_PX * max(sw, sh):
        raise InputError(
            f"calibration is for {cam.width}x{cam.height} frames but the source is {sw}x{sh}"
            " (different aspect ratio)",
            where,
        )
    return cam.scaled_to(sw, sh)


def read_camera(path: Path, default_size: tuple[int, int]) -> tuple[Camera, str]:
    """A calibration file (JSON, or OpenCV YAML/XML) -> (Camera at its own size, origin).

    ``default_size`` (w, h) is used when the file does not state the image size.
    """
    if not path.is_file():
        raise InputError("calibration file not found", path)
    if path.suffix.lower() in OPENCV_STORAGE_SUFFIXES:
        return _from_opencv_storage(path, default_size), "calibration"
    try:
        doc: Any = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as err:
        raise InputError(f"not a readable calibration JSON: {err}", path) from None
    if not isinstance(doc, dict):
        raise InputError("calibration JSON must be an object", path)
    inner = doc.get("intrinsics", doc)
    if not isinstance(inner, dict):
        raise InputError("'intrinsics' must be an object with fx, fy, cx, cy", path)
    origin = "flight.json" if "intrinsics" in doc and "frames" in doc else "calibration"
    return _from_mapping(inner, default_size, path), origin


def _from_mapping(d: dict[str, Any], default_size: tuple[int, int], path: Path) -> Camera:
    try:
        if all(k in d for k in ("fx", "fy", "cx", "cy")):
            fx, fy, cx, cy = (float(d[k]) for k in ("fx", "fy", "cx", "cy"))
            k = np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1]])
            offset = float(d.get("pixel_center_offset", DRONECAP_OFFSET))
        else:
            k = d.get("K", d.get("camera_matrix"))
            if k is None:
                raise KeyError("fx, fy, cx, cy (or a 3x3 K / camera_matrix)")
            k = np.asarray(k, float).reshape(3, 3)
            offset = float(d.get("pixel_center_offset", OPENCV_OFFSET))
        dist = next((d[n] for n in ("distortion", "dist", "distortion_coefficients") if n in d), [])
        size = d.get("size") or (
            d.get("width", d.get("image_width")),
            d.get("height", d.get("image_height")),
        )
        w, h = (int(v) if v is not None else v for v in size)
    except (KeyError, IndexError, TypeError, ValueError) as err:
        raise InputError(f"calibration JSON lacks usable intrinsics: {err}", path) from None
    model = str(d.get("model", "pinhole")).lower()
    size = (w or default_size[0], h or default_size[1])
    return _camera(_to_dronecap(k, offset), dist, model, size, path)


def _from_opencv_storage(path: Path, default_size: tuple[int, int]) -> Camera:
    import cv2

    try:
        fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    except (cv2.error, SystemError) as err:  # a parse error surfaces as either
        cause = str(getattr(err, "__cause__", None) or err).strip().splitlines()[-1][-120:]
        raise InputError(f"not an OpenCV YAML/XML file: {cause}", path) from None
    try:
        if not fs.isOpened():
            raise InputError("not an OpenCV YAML/XML file OpenCV can open", path)
        k = _storage_matrix(fs.getNode("camera_matrix"))
        if k is None or k.size != 9:
            raise InputError("has no 3x3 camera_matrix", path)
        dist = _storage_matrix(fs.getNode("distortion_coefficients"))
        w, h = (int(fs.getNode(n).real()) for n in ("image_width", "image_height"))
        model = "pinhole"
        for name in ("model", "distortion_model"):
            node = fs.getNode(name)
            if node.isString():
                model = ROS_MODELS.get(node.string().lower(), node.string().lower())
        if fs.getNode("fisheye_model").real() != 0:
            model = "fisheye"
    finally:
        fs.release()
    size = (w, h) if w > 0 and h > 0 else default_size
    return _camera(_to_dronecap(k, OPENCV_OFFSET), [] if dist is None else dist, model, size, path)


def _storage_matrix(node) -> np.ndarray | None:
    """A matrix node of a FileStorage: OpenCV's ``!!opencv-matrix`` or ROS camera_info's plain
    map ``{rows, cols, data: [...]}``; None when absent."""
    if node.isMap() and node.getNode("dt").empty() and not node.getNode("data").empty():
        data = node.getNode("data")
        return np.array([data.at(i).real() for i in range(data.size())], float)
    return None if node.empty() else node.mat()


def _camera(k, dist, model: str, size: tuple[int, int], path: Path) -> Camera:
    """Camera from an OpenCV K and distortion vector; InputError when it cannot be one."""
    if model not in MODELS:
        raise InputError(f"model must be one of {', '.join(MODELS)}, found {model!r}", path)
    coeffs = np.asarray(dist, float).ravel()
    if not np.all(np.isfinite(coeffs)):
        raise InputError(f"non-finite distortion {coeffs.tolist()}", path)
    if model == "fisheye" and len(coeffs) == 0:
        coeffs = np.zeros(4)
    if model == "pinhole" and len(coeffs) > 8 and not coeffs[8:].any():
        coeffs = coeffs[:8]  # thin-prism/tilt terms present but zero
    try:
        return Camera.from_opencv(k, coeffs, size[0], size[1], fisheye=model == "fisheye")
    except ValueError as err:
        raise InputError(f"distortion cannot be used: {err}", path) from None


def _to_dronecap(k: np.ndarray, offset: float) -> np.ndarray:
    """K [3, 3] of a file whose pixel centres sit at integer + ``offset`` -> dronecap's K."""
    k = np.array(k, float).reshape(3, 3)
    k[:2, 2] += DRONECAP_OFFSET - offset
    return k


def calibration_record(cam: Camera, **fields: Any) -> dict[str, Any]:
    """The calibration JSON object of ``cam`` (what :func:`read_camera` reads back):
    ``K``, ``distortion`` (OpenCV order), ``model``, ``width``, ``height``, the flat
    ``fx, fy, cx, cy`` for readers that want them and ``pixel_center_offset`` 0.5 (K is in
    dronecap's convention: subtract 0.5 from cx, cy for OpenCV's), then ``fields``."""
    coeffs = [float(x) for x in cam.opencv_coeffs()]
    if not cam.is_fisheye:  # OpenCV's usual 5-vector unless k4..k6 are used
        coeffs = (coeffs + [0.0] * 5)[: 8 if any(coeffs[5:]) else 5]
    out: dict[str, Any] = {
        "model": "fisheye" if cam.is_fisheye else "pinhole",
        "width": cam.width,
        "height": cam.height,
        "K": cam.matrix().tolist(),
        "distortion": coeffs,
        "fx": cam.fx,
        "fy": cam.fy,
        "cx": cam.cx,
        "cy": cam.cy,
        "pixel_center_offset": DRONECAP_OFFSET,
    }
    out.update(fields)
    return _finite_json(out)


def write_calibration(path: str | Path, record: dict[str, Any]) -> None:
    """Write a calibration record atomically: pretty JSON, or for a ``.yml``/``.yaml``/``.xml``
    path OpenCV FileStorage as OpenCV's calibration samples write it (``camera_matrix`` in
    OpenCV's pixel convention, ``distortion_coefficients``, ``image_width``, ``image_height``,
    ``avg_reprojection_error``, ``fisheye_model``) for tools that read those."""
    from dronecap.files import atomic_output

    suffix = Path(path).suffix.lower()
    text = (
        _opencv_storage_text(record, suffix)
        if suffix in OPENCV_STORAGE_SUFFIXES
        else json.dumps(record, indent=1) + "\n"
    )
    with atomic_output(path) as tmp:
        tmp.write_text(text)


def _opencv_storage_text(record: dict[str, Any], suffix: str) -> str:
    import cv2

    fs = cv2.FileStorage(suffix, cv2.FILE_STORAGE_WRITE | cv2.FILE_STORAGE_MEMORY)
    fs.write("image_width", int(record["width"]))
    fs.write("image_height", int(record["height"]))
    fs.write("model", record["model"])
    fs.write("fisheye_model", int(record["model"] == "fisheye"))
    k = np.array(record["K"], float)  # dronecap's convention ...
    k[:2, 2] -= DRONECAP_OFFSET - OPENCV_OFFSET  # ... to OpenCV's: cx, cy - 0.5
    fs.write("camera_matrix", k)
    fs.write("distortion_coefficients", np.asarray(record["distortion"], float).reshape(1, -1))
    if record.get("rms") is not None:
        fs.write("avg_reprojection_error", float(record["rms"]))
    return fs.releaseAndGetString()


def _finite_json(x: Any) -> Any:
    """Replace non-finite floats by None so the JSON stays standard."""
    if isinstance(x, dict):
        return {k: _finite_json(v) for k, v in x.items()}
    if isinstance(x, list | tuple):
        return [_finite_json(v) for v in x]
    if isinstance(x, float) and not math.isfinite(x):
        return None
    return x
