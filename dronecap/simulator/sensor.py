"""The simulated camera: a :class:`dronecap.camera.Camera` lens plus the sensor's defects.

:class:`Sensor` holds what happens to light between the scene and an 8-bit frame:

- **lens** (``dronecap.camera.Camera``): focal length, principal point (possibly off centre) and
  OpenCV radial distortion; the renderer casts one ray per pixel centre through
  ``Camera.undistort_points``, so the lens model *is* the ground truth;
- **vignetting**: relative illumination ``1 - v * (r / r_corner)^2`` about the principal point
  (``v`` = light lost at the farthest corner);
- **motion blur**: the frame integrates the flight's own motion over ``exposure_s`` (sub-frame
  renders, see :mod:`dronecap.simulator.render`);
- **auto-exposure drift**: a slowly varying gain of relative amplitude ``exposure_drift``;
- **noise**: signal-dependent, variance ``shot_noise * DN + read_noise^2`` (DN = 8-bit digital
  numbers before quantisation);
- **JPEG**: the frame is JPEG-compressed at ``jpeg_quality`` and decoded (0 = raw).

:data:`DEFECT_DEFAULTS` gives the realistic level each defect flag of ``dronecap simulate`` takes
when given without a value; :func:`sensor_preset` builds the named combinations
(``clean`` = the original simulator, ``aideck`` = an AI-deck HM01B0 streaming over Wi-Fi).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from dronecap.camera import Camera

# Realistic level of each defect when its flag is given without a value (one place for them).
# Lens and sensor figures follow published AI-deck / HM01B0 calibrations and datasheets: radial
# k1 -0.07..-0.10, a principal point 30-60 px off the centre row at 324x244, strong vignetting of
# the M12 lens, noisy frames at the analogue gain an indoor flight needs, exposures near the
# frame time, JPEG streaming, and a lossy Wi-Fi link.
DEFECT_DEFAULTS: dict[str, object] = {
    "distortion": (-0.1, 0.02),  # OpenCV k1, k2
    "principal_offset": (0.03, 0.15),  # (dx / width, dy / height) of the principal point
    "vignetting": 0.35,  # light lost at the farthest corner
    "noise": (3.0, 0.3),  # read noise DN, shot-noise DN of variance per DN
    "blur": 30.0,  # exposure time, ms
    "exposure_drift": 0.35,  # relative amplitude of the auto-exposure gain drift
    "jpeg": 60,  # JPEG quality
    "drop": 0.05,  # fraction of frames lost by the link (in bursts)
    "duplicate": 0.03,  # fraction of frames delivered as a repeat of the previous one
    "torn": 0.03,  # fraction of frames whose bottom part is lost (black, gray or shifted)
}

CLEAN_FOCAL_FRACTION = 0.75  # fx = fy = 0.75 * width: the clean 160 px camera's 67 deg view
MAX_SUBFRAMES = 8  # sub-frame renders per frame for the clean camera's 1/60 s exposure


@dataclass(frozen=True)
class Sensor:
    """Lens plus sensor of the simulated drone camera (pixels, seconds, 8-bit DN)."""

    lens: Camera = Camera(120.0, 120.0, 80.0, 80.0, 160, 160)
    exposure_s: float = 1 / 60  # shutter time
    read_noise: float = 1.5  # DN
    shot_noise: float = 0.04  # DN of variance per DN of signal
    vignetting: float = 0.0  # fraction of light lost at the farthest corner
    exposure_drift: float = 0.1  # relative amplitude of the exposure-gain drift
    jpeg_quality: int = 0  # 0: raw frames, else JPEG quality 1..100
    max_subframes: int = MAX_SUBFRAMES

    def problems(self) -> list[str]:
        """What makes this sensor unusable (empty when fine)."""
        out = [f"lens: {p}" for p in self.lens.problems()]
        checks = {
            "exposure time": 0 < self.exposure_s <= 1.0,
            "read noise": 0 <= self.read_noise <= 100,
            "shot noise": 0 <= self.shot_noise <= 100,
            "vignetting": 0 <= self.vignetting < 1,
            "exposure drift": 0 <= self.exposure_drift < 1,
            "JPEG quality": self.jpeg_quality == 0 or 1 <= self.jpeg_quality <= 100,
        }
        out += [f"{name} out of range" for name, ok in checks.items() if not ok]
        return out

    def describe(self) -> dict[str, object]:
        """JSON-able record of the sensor (lens excluded: flight.json has it as intrinsics)."""
        d = dataclasses.asdict(self)
        d.pop("lens")
        return d


def default_lens(width: int, height: int, focal: float | None = None) -> Camera:
    """Pinhole lens centred on a ``width`` x ``height`` image; ``focal`` in pixels (default:
    :data:`CLEAN_FOCAL_FRACTION` of the width)."""
    f = CLEAN_FOCAL_FRACTION * width if focal is None else float(focal)
    return Camera(f, f, width / 2, height / 2, int(width), int(height))


def with_lens_defects(
    lens: Camera,
    distortion: tuple[float, ...] | None = None,
    principal_offset: tuple[float, float] | None = None,
) -> Camera:
    """``lens`` with OpenCV radial ``distortion`` (k1, k2[, k3]) and its principal point moved by
    ``principal_offset`` (fractions of the width and height)."""
    if principal_offset is not None:
        dx, dy = principal_offset
        lens = dataclasses.replace(
            lens, cx=lens.cx + dx * lens.width, cy=lens.cy + dy * lens.height
        )
    if distortion is not None and any(distortion):
        k = (tuple(distortion) + (0.0, 0.0, 0.0))[:3]
        if k[2] == 0.0:
            lens = dataclasses.replace(lens, model="RADIAL", distortion=k[:2])
        else:
            lens = dataclasses.replace(
                lens, model="FULL_OPENCV", distortion=(k[0], k[1], 0.0, 0.0, k[2], 0.0, 0.0, 0.0)
            )
    return lens


def sensor_preset(name: str) -> Sensor:
    """``clean``: the original 160x160 simulator; ``aideck``: the AI-deck's HM01B0 at 324x244
    (f = 184 px) with every lens and sensor defect at its default level; ``aideck-162``: the same
    binned to 162x162 (f = 92 px)."""
    if name == "clean":
        return Sensor()
    sizes = {"aideck": (324, 244, 184.0), "aideck-162": (162, 162, 92.0)}
    if name not in sizes:
        raise ValueError(f"unknown sensor {name!r}, expected clean, {', '.join(sizes)}")
    w, h, f = sizes[name]
    lens = with_lens_defects(
        default_lens(w, h, f),
        DEFECT_DEFAULTS["distortion"],  # type: ignore[arg-type]
        DEFECT_DEFAULTS["principal_offset"],  # type: ignore[arg-type]
    )
    read, shot = DEFECT_DEFAULTS["noise"]  # type: ignore[misc]
    return Sensor(
        lens=lens,
        exposure_s=float(DEFECT_DEFAULTS["blur"]) / 1000,  # type: ignore[arg-type]
        read_noise=read,
        shot_noise=shot,
        vignetting=float(DEFECT_DEFAULTS["vignetting"]),  # type: ignore[arg-type]
        exposure_drift=float(DEFECT_DEFAULTS["exposure_drift"]),  # type: ignore[arg-type]
        jpeg_quality=int(DEFECT_DEFAULTS["jpeg"]),  # type: ignore[call-overload]
        max_subframes=2 * MAX_SUBFRAMES,
    )


def vignette(lens: Camera, strength: float) -> np.ndarray:
    """Relative illumination float32 [H, W] of each pixel: ``1 - strength * (r / r_max)^2`` with
    ``r`` the distance of the pixel centre from the principal point and ``r_max`` that of the
    farthest image corner (so the darkest corner gets ``1 - strength``)."""
    v, u = np.mgrid[0 : lens.height, 0 : lens.width].astype(np.float64)
    r2 = (u + 0.5 - lens.cx) ** 2 + (v + 0.5 - lens.cy) ** 2
    corners = [
        (x - lens.cx) ** 2 + (y - lens.cy) ** 2 for x in (0, lens.width) for y in (0, lens.height)
    ]
    return (1.0 - strength * r2 / max(corners)).astype(np.float32)


def exposure_gain(u: np.ndarray, seed: int, amplitude: float) -> np.ndarray:
    """Auto-exposure gain [T] around 0.95 at normalised flight times ``u`` [T]: two slow
    oscillations of total relative amplitude ``amplitude`` (0.1 = the clean camera's +-10 %)."""
    p = np.random.default_rng([seed, 4]).uniform(0, 2 * np.pi, 2)
    wave = 0.7 * np.sin(2 * np.pi * 1.3 * u + p[0]) + 0.3 * np.sin(2 * np.pi * 3.1 * u + p[1])
    return 0.95 * (1.0 + amplitude * wave)


def expose(
    radiance: np.ndarray, gain: float, sensor: Sensor, rng: np.random.Generator
) -> np.ndarray:
    """Linear image [H, W] (~[0, 1], vignetting applied) -> uint8 [H, W]: gain, 8-bit scale,
    noise of variance ``shot * DN + read^2``, quantisation, then JPEG if the sensor streams it."""
    dn = np.clip(radiance * gain * 255.0, 0.0, 255.0)
    sigma = np.sqrt(sensor.shot_noise * dn + sensor.read_noise**2)
    noisy = dn + sigma * rng.standard_normal(dn.shape)
    frame = np.clip(np.rint(noisy), 0, 255).astype(np.uint8)
    return jpeg_roundtrip(frame, sensor.jpeg_quality) if sensor.jpeg_quality else frame


def jpeg_roundtrip(frame: np.ndarray, quality: int) -> np.ndarray:
    """uint8 [H, W] frame after JPEG compression at ``quality`` and decoding (OpenCV)."""
    import cv2

    ok, buf = cv2.imencode(".jpg", frame, [cv2.IMWRITE_JPEG_QUALITY, int(quality)])
    if not ok:  # pragma: no cover - OpenCV always encodes a uint8 gray image
        raise RuntimeError("OpenCV failed to encode a JPEG")
    return cv2.imdecode(buf, cv2.IMREAD_GRAYSCALE)
