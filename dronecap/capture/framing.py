"""Frame geometry: gray conversion, crop to the target aspect, area resize, and the camera.

Coordinates are continuous pixel coordinates with pixel centres at integer + 0.5 (OpenCV's
convention, the one :mod:`dronecap.datasets` stores). In those coordinates a crop that starts at
pixel column ``x0`` shifts every point by ``-x0`` and a resize by ``s = new / old`` multiplies every
point by ``s`` -- exactly what ``cv2.resize`` does to pixel centres -- so a camera
``(fx, fy, cx, cy)`` becomes ``(fx s_x, fy s_y, (cx - x0) s_x, (cy - y0) s_y)`` with its lens
distortion unchanged (:meth:`Framing.camera`, via ``Camera.cropped`` and ``Camera.scaled_to``).

Gray is ITU-R BT.601 luma, ``Y = 0.299 R + 0.587 G + 0.114 B`` (``cv2.COLOR_BGR2GRAY``), on the
gamma-encoded 8-bit values as decoded; this is also the Y plane a YUV video stores.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from dronecap.camera import Camera

LUMA_WEIGHTS = {"r": 0.299, "g": 0.587, "b": 0.114}  # BT.601, as cv2.COLOR_BGR2GRAY


@dataclass(frozen=True)
class Framing:
    """How a source frame becomes an output frame: crop box, then resize to ``size``.

    ``box`` is ``(x0, y0, w, h)`` in source pixels; ``size`` is the output ``(width, height)``.
    """

    source_size: tuple[int, int]  # (width, height) of the decoded frames
    box: tuple[int, int, int, int]
    size: tuple[int, int]

    @property
    def scale(self) -> tuple[float, float]:
        """(s_x, s_y) = output size / crop size."""
        return self.size[0] / self.box[2], self.size[1] / self.box[3]

    @property
    def upsamples(self) -> bool:
        """True when the crop is smaller than the output along some axis (no new detail)."""
        return self.box[2] < self.size[0] or self.box[3] < self.size[1]

    def camera(self, cam: Camera) -> Camera:
        """The camera of the output frames: ``cam`` (of the source frames, same width and
        height) through the crop and the resize. The distortion acts on normalised
        coordinates, so it is carried through unchanged (the frames are not undistorted)."""
        x0, y0, w, h = self.box
        return cam.cropped(x0, y0, w, h).scaled_to(*self.size)

    def apply(self, frame: np.ndarray) -> np.ndarray:
        """Crop, convert to gray and resize one decoded frame (uint8/uint16 [H_src, W_src] or
        [H_src, W_src, 3|4] BGR(A)) -> uint8 [h, w]. Cropping first converts fewer pixels; gray
        and the area average are both linear, so the order does not change the result."""
        import cv2

        x0, y0, w, h = self.box
        crop = to_gray(frame[y0 : y0 + h, x0 : x0 + w])
        if (w, h) == self.size:
            return np.ascontiguousarray(crop)
        # INTER_AREA averages when shrinking; when enlarging OpenCV falls back to bilinear.
        return cv2.resize(crop, self.size, interpolation=cv2.INTER_AREA)


def parse_numbers(text: str, count: int, kind: type, what: str) -> tuple:
    """``"1,2,3"`` -> a tuple of ``count`` values of type ``kind``; ``ValueError(what ...)``."""
    try:
        values = tuple(kind(v) for v in text.split(","))
    except ValueError:
        values = ()
    if len(values) != count:
        raise ValueError(f"{what}, got {text!r}")
    return values


MAX_OUTPUT_SIDE = 4096  # pixels: the largest ingest --size


def parse_size(text: str) -> tuple[int, int]:
    """``"160"`` or ``"160x120"`` -> (width, height) in pixels."""
    parts = text.lower().replace("×", "x").split("x")
    if len(parts) == 1:
        parts = parts * 2
    w, h = (int(p) for p in parts)
    if w < 8 or h < 8:
        raise ValueError(f"output size {w}x{h} is too small (minimum 8x8)")
    if max(w, h) > MAX_OUTPUT_SIDE:  # larger decodes at ~24 s a frame for no added detail
        raise ValueError(f"output size {w}x{h} is too large (at most {MAX_OUTPUT_SIDE} a side)")
    return w, h


def make_framing(source_size: tuple[int, int], size: tuple[int, int], crop: str) -> Framing:
    """Build the crop box for a source frame size.

    Args:
        source_size: (width, height) of the decoded frames.
        size: output (width, height).
        crop: ``"center"`` (largest box of the output aspect, centred; odd leftovers go to the
            right/bottom), ``"stretch"`` (whole frame, aspect not kept: fx and fy scale
            differently), or ``"X,Y,W,H"`` (an explicit box in source pixels).
    """
    sw, sh = source_size
    if crop == "stretch":
        box = (0, 0, sw, sh)
    elif crop in ("center", "centre"):
        aspect = size[0] / size[1]
        if sw / sh > aspect:  # too wide: cut left and right
            w = min(sw, max(1, round(sh * aspect)))
            box = ((sw - w) // 2, 0, w, sh)
        else:  # too tall: cut top and bottom
            h = min(sh, max(1, round(sw / aspect)))
            box = (0, (sh - h) // 2, sw, h)
    else:
        x0, y0, w, h = parse_numbers(crop, 4, int, "crop must be 'center', 'stretch' or 'X,Y,W,H'")
        if x0 < 0 or y0 < 0 or w < 1 or h < 1 or x0 + w > sw or y0 + h > sh:
            raise ValueError(f"crop box {crop} does not fit inside the {sw}x{sh} frames")
        box = (x0, y0, w, h)
    return Framing(source_size=(sw, sh), box=box, size=size)


def to_gray(frame: np.ndarray) -> np.ndarray:
    """Decoded frame (uint8/uint16 [H, W], [H, W, 3] BGR or [H, W, 4] BGRA) -> uint8 [H, W]."""
    import cv2

    if frame.dtype == np.uint16:
        frame = (frame >> 8).astype(np.uint8)
    elif frame.dtype != np.uint8:
        frame = np.clip(frame, 0, 255).astype(np.uint8)
    if frame.ndim == 2:
        return frame
    if frame.shape[2] == 1:
        return frame[:, :, 0]
    code = cv2.COLOR_BGRA2GRAY if frame.shape[2] == 4 else cv2.COLOR_BGR2GRAY
    return cv2.cvtColor(frame, code)
