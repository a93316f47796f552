"""The one camera type of dronecap: pinhole intrinsics plus a lens-distortion model.

Every stage (ingest, SfM, datasets, the trainer's rays, exports) uses :class:`Camera`.
Coordinates are continuous pixel coordinates of the stored image with pixel centres at
integer + 0.5 (OpenCV's convention): pixel index (u, v) is the point (u + 0.5, v + 0.5).

Distortion models are named as COLMAP names them, with their extra parameters in COLMAP's
order (what SfM estimates and stores); each maps onto OpenCV's coefficient vector, so OpenCV
does all the maths (``cv2.undistortPoints``, ``cv2.projectPoints`` and their fisheye twins):

============== ======================== =====================================
model          ``distortion``           OpenCV coefficients
============== ======================== =====================================
PINHOLE        ()                       none
SIMPLE_RADIAL  (k,)                     (k, 0, 0, 0)
RADIAL         (k1, k2)                 (k1, k2, 0, 0)
OPENCV         (k1, k2, p1, p2)         (k1, k2, p1, p2)
FULL_OPENCV    (k1, k2, p1, p2, k3..k6) (k1, k2, p1, p2, k3, k4, k5, k6)
OPENCV_FISHEYE (k1, k2, k3, k4)         cv2.fisheye (k1, k2, k3, k4)
============== ======================== =====================================
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np

# model -> number of distortion parameters
DISTORTION_PARAMS: dict[str, int] = {
    "PINHOLE": 0,
    "SIMPLE_RADIAL": 1,
    "RADIAL": 2,
    "OPENCV": 4,
    "FULL_OPENCV": 8,
    "OPENCV_FISHEYE": 4,
}
FISHEYE = "OPENCV_FISHEYE"


@dataclass(frozen=True)
class Camera:
    """Intrinsics in pixels of a ``width`` x ``height`` image, plus a distortion model.

    ``fx, fy`` focal lengths (px), ``cx, cy`` principal point (px, continuous coordinates),
    ``model`` one of :data:`DISTORTION_PARAMS`, ``distortion`` its parameters (COLMAP order).
    """

    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int
    model: str = "PINHOLE"
    distortion: tuple[float, ...] = ()

    # -- checks and conversions ---------------------------------------------------------------
    def problems(self) -> list[str]:
        """What is wrong with this camera (empty when usable): non-finite or non-positive
        values, an unknown model, a parameter count that does not match the model."""
        out = []
        vals = (self.fx, self.fy, self.cx, self.cy, *self.distortion)
        if not all(_is_finite_number(x) for x in vals):
            out.append(f"non-finite intrinsics {vals}")
        elif not (self.fx > 0 and self.fy > 0):
            out.append(f"focal lengths must be positive, found fx={self.fx}, fy={self.fy}")
        if not (int(self.width) > 0 and int(self.height) > 0):
            out.append(f"image size must be positive, found {self.width}x{self.height}")
        if self.model not in DISTORTION_PARAMS:
            out.append(
                f"unknown camera model {self.model!r}; known: {', '.join(DISTORTION_PARAMS)}"
            )
        elif len(self.distortion) != DISTORTION_PARAMS[self.model]:
            out.append(
                f"camera model {self.model} takes {DISTORTION_PARAMS[self.model]} distortion "
                f"parameters, found {len(self.distortion)}"
            )
        return out

    @property
    def is_fisheye(self) -> bool:
        """True for the OpenCV fisheye (equidistant) model."""
        return self.model == FISHEYE

    @property
    def is_pinhole(self) -> bool:
        """True when there is no distortion (all parameters zero counts as none; a fisheye
        is never a pinhole: its projection is equidistant even with zero coefficients)."""
        return not self.is_fisheye and not any(self.distortion)

    def matrix(self) -> np.ndarray:
        """3x3 K matrix, float64."""
        return np.array([[self.fx, 0, self.cx], [0, self.fy, self.cy], [0, 0, 1]], float)

    def opencv_coeffs(self) -> np.ndarray:
        """OpenCV's distortion vector (float64 [4] or [8]; fisheye: [4] for ``cv2.fisheye``)."""
        d = list(self.distortion)
        if self.model in ("PINHOLE", "SIMPLE_RADIAL", "RADIAL"):
            d = (d + [0.0] * 4)[:4]
        return np.asarray(d, np.float64)

    @classmethod
    def from_opencv(
        cls, k: np.ndarray, dist, width: int, height: int, fisheye: bool = False
    ) -> Camera:
        """A camera from an OpenCV K [3, 3] and distortion vector (4, 5, 8 values or none;
        fisheye: 4). Raises ValueError for other lengths (thin-prism/tilted models)."""
        d = [float(x) for x in np.asarray(dist if dist is not None else [], float).ravel()]
        if fisheye:
            if len(d) != 4:
                raise ValueError(f"a fisheye distortion has 4 coefficients, found {len(d)}")
            model = FISHEYE
        elif not any(d):
            model, d = "PINHOLE", []
        elif len(d) == 4 or (len(d) in (5, 8) and not any(d[4:])):
            model, d = "OPENCV", d[:4]  # k3..k6 zero: the simpler model, same maths
        elif len(d) in (5, 8):
            model, d = "FULL_OPENCV", (d + [0.0] * 3)[:8]
        else:
            raise ValueError(f"unsupported OpenCV distortion with {len(d)} coefficients")
        k = np.asarray(k, float)
        return cls(
            float(k[0, 0]), float(k[1, 1]), float(k[0, 2]), float(k[1, 2]),
            int(width), int(height), model, tuple(d),
        )  # fmt: skip

    def scaled(self, sx: float, sy: float) -> Camera:
        """The camera after resizing the image by (sx, sy) = new size / old size (distortion
        acts on normalised coordinates, so it is unchanged)."""
        return dataclasses.replace(
            self,
            fx=self.fx * sx,
            fy=self.fy * sy,
            cx=self.cx * sx,
            cy=self.cy * sy,
            width=round(self.width * sx),
            height=round(self.height * sy),
        )

    def scaled_to(self, width: int, height: int) -> Camera:
        """The same camera for an image of ``width`` x ``height`` (same field of view)."""
        return dataclasses.replace(
            self.scaled(width / self.width, height / self.height),
            width=int(width),
            height=int(height),
        )

    def cropped(self, x0: float, y0: float, width: int, height: int) -> Camera:
        """The camera of the ``width`` x ``height`` window starting at pixel (x0, y0)."""
        return dataclasses.replace(
            self, cx=self.cx - x0, cy=self.cy - y0, width=int(width), height=int(height)
        )

    def pinhole(self) -> Camera:
        """The same intrinsics without distortion."""
        return dataclasses.replace(self, model="PINHOLE", distortion=())

    # -- geometry -------------------------------------------------------------------------------
    def undistort_points(self, uv: np.ndarray) -> np.ndarray:
        """Normalised image coordinates (x/z, y/z) of pixels ``uv`` [N, 2] (continuous pixel
        coordinates, centres at +0.5) -> float64 [N, 2]. Exact inverse of :meth:`project` up to
        OpenCV's iterative solver (< 1e-3 px inside the image for realistic lenses)."""
        import cv2

        pts = np.asarray(uv, np.float64).reshape(-1, 1, 2)
        if self.is_pinhole:
            k = self.matrix()
            return np.stack(
                [(pts[:, 0, 0] - k[0, 2]) / k[0, 0], (pts[:, 0, 1] - k[1, 2]) / k[1, 1]], 1
            )
        if self.is_fisheye:
            out = cv2.fisheye.undistortPoints(pts, self.matrix(), self.opencv_coeffs())
        else:
            crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-12)
            k, d = self.matrix(), self.opencv_coeffs()
            if hasattr(cv2, "undistortPointsIter"):  # OpenCV 4.x spells the iterative form so
                out = cv2.undistortPointsIter(pts, k, d, None, None, crit)
            else:
                out = cv2.undistortPoints(pts, k, d, R=None, P=None, criteria=crit)
        return out.reshape(-1, 2)

    def project(self, xyz: np.ndarray) -> np.ndarray:
        """Pixels (continuous coordinates) of camera-frame points ``xyz`` [N, 3] (z > 0)
        -> float64 [N, 2], through the distortion."""
        import cv2

        pts = np.asarray(xyz, np.float64).reshape(-1, 1, 3)
        zero = np.zeros(3)
        if self.is_fisheye:
            out, _ = cv2.fisheye.projectPoints(pts, zero, zero, self.matrix(), self.opencv_coeffs())
        else:
            coeffs = None if self.is_pinhole else self.opencv_coeffs()
            out, _ = cv2.projectPoints(pts, zero, zero, self.matrix(), coeffs)
        return out.reshape(-1, 2)

    def pixel_directions(self) -> np.ndarray:
        """Camera-frame ray directions (x/z, y/z, 1) through every pixel centre, float32
        [H, W, 3] (not unit length), undistorted through the lens model."""
        v, u = np.mgrid[0 : self.height, 0 : self.width]
        uv = np.stack([u.ravel() + 0.5, v.ravel() + 0.5], 1)
        xy = self.undistort_points(uv)
        d = np.concatenate([xy, np.ones((xy.shape[0], 1))], 1)
        return d.reshape(self.height, self.width, 3).astype(np.float32)


def _is_finite_number(x: object) -> bool:
    try:
        return not isinstance(x, str | bytes | bool) and math.isfinite(float(x))  # type: ignore[arg-type]
    except (TypeError, ValueError):
        return False
