"""The simulate stage: render a nano-drone flight through a lens, a sensor and a lossy link.

Ground truth (``flight.json``: beside the video, or inside a capture folder)::

    {"fps": 30,
     "intrinsics": {"fx", "fy", "cx", "cy", "width", "height"[, "model": "pinhole",
                    "distortion": [k1, k2, p1, p2, k3]]},   # pixels, centres at +0.5; OpenCV order
     "frames": [{"index": k, "timestamp": t, "c2w": 4x4, "source_frame": s, "frame_id": s % 256,
                 "frame_timestamp": us, ["shows": j], ["tear": {"row", "kind", "shift"}],
                 ["file": name]}, ...],
     "stream": {"source_frames": N, "delivered": M, "dropped": [...], "duplicated": [...],
                "torn": [...]},
     "sensor": {...}, "scene": {...}, "format": "mp4" | "nanocockpit" | "pulp-dronet",
     ["telemetry": {...}]}

``frames`` lists the DELIVERED frames in order: ``index`` k is the video frame number or the
position of the file in the folder's natural order (what ingest stores as ``source_index``);
``source_frame`` s is the camera's frame number (dropped ones are missing from the list and
listed under ``stream.dropped``). ``c2w`` is camera-to-world in OpenCV camera axes, metres, at
the middle of the exposure of the image the frame SHOWS (a duplicate shows an earlier frame
``shows``; its ``timestamp`` = that image's capture time, seconds from the first frame). A torn
frame's top rows (above ``tear.row``) are exact. Without defects this is the original simulator's
output, byte for byte; the same seed gives the same capture.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from dronecap.errors import InputError, check_option
from dronecap.simulator import formats, telemetry
from dronecap.simulator.flights import Flight
from dronecap.simulator.render import Renderer
from dronecap.simulator.scenes import SCENES
from dronecap.simulator.sensor import (
    DEFECT_DEFAULTS,
    Sensor,
    expose,
    exposure_gain,
    sensor_preset,
    vignette,
)
from dronecap.simulator.stream import Delivered, LinkDefects, plan_stream, tear

FPS = 30.0


@dataclass(frozen=True)
class Capture:
    """What to simulate besides the scene: the camera, the link and the onboard telemetry."""

    sensor: Sensor = field(default_factory=Sensor)
    link: LinkDefects = field(default_factory=LinkDefects)
    state_noise: telemetry.StateNoise = field(default_factory=telemetry.StateNoise)
    sensor_name: str = "custom"

    def problems(self) -> list[str]:
        """Everything out of range (empty when the capture can be simulated)."""
        return self.sensor.problems() + self.link.problems() + self.state_noise.problems()


def capture_preset(name: str) -> Capture:
    """The capture of a named sensor (:func:`~dronecap.simulator.sensor.sensor_preset`); the
    AI-deck ones stream over a lossy link (drops, duplicates, tears at their default levels)."""
    link = LinkDefects()
    if name.startswith("aideck"):
        link = LinkDefects(
            *(float(DEFECT_DEFAULTS[k]) for k in ("drop", "duplicate", "torn"))  # type: ignore[arg-type]
        )
    return Capture(sensor_preset(name), link, sensor_name=name)


def intrinsics_record(sensor: Sensor) -> dict[str, object]:
    """flight.json ``intrinsics``: the calibration-JSON keys (OpenCV distortion order)."""
    lens = sensor.lens
    out: dict[str, object] = {
        "fx": lens.fx, "fy": lens.fy, "cx": lens.cx, "cy": lens.cy,
        "width": lens.width, "height": lens.height,
    }  # fmt: skip
    if not lens.is_pinhole:
        d = [float(x) for x in lens.opencv_coeffs()]
        out["model"] = "pinhole"
        out["distortion"] = (d + [0.0] * 5)[:5]
    return out


class SimulatedFlight:
    """A flight of ``frames`` source frames at 30 Hz through ``capture``; renders lazily."""

    def __init__(
        self,
        scene_name: str,
        frames: int,
        seed: int,
        capture: Capture,
        part: tuple[float, float] = (0.0, 1.0),
        scene_seed: int | None = None,
    ) -> None:
        """``seed`` draws the flight's noise, exposure, link and onboard state; ``scene_seed``
        (default ``seed``) the scene and its route, of which the drone flies ``part``."""
        if scene_name not in SCENES:
            raise InputError(f"unknown scene {scene_name!r}, expected one of {sorted(SCENES)}")
        check_option("frames", frames, minimum=2)
        check_option("seed", seed, minimum=0)
        if problems := capture.problems():
            raise InputError("; ".join(problems))
        self.scene_name, self.frames, self.seed, self.capture = scene_name, frames, seed, capture
        scene_seed = seed if scene_seed is None else scene_seed
        self.scene = SCENES[scene_name](scene_seed)
        self.flight = Flight(scene_name, scene_seed, part)
        sensor = capture.sensor
        self.renderer = Renderer(self.scene, sensor.lens)
        self.duration = frames / FPS
        u = np.arange(frames) / frames
        self.poses = self.flight.pose(u, frames)  # [N, 4, 4] every source frame
        self.gain = exposure_gain(u, seed, sensor.exposure_drift)
        self.delivered = plan_stream(frames, capture.link, sensor.lens.height, seed)
        self._vignette = vignette(sensor.lens, sensor.vignetting) if sensor.vignetting else None

    def pose_at(self, seconds: np.ndarray) -> np.ndarray:
        """Camera-to-world [T, 4, 4] at flight times ``seconds`` [T] (0 = first frame)."""
        return self.flight.pose(np.asarray(seconds) / self.duration, self.frames)

    def render_source(self, s: int) -> np.ndarray:
        """The camera's uint8 [H, W] frame ``s`` (motion blur, vignetting, exposure, noise,
        JPEG), before the link."""
        sensor, u = self.capture.sensor, s / self.frames
        half = 0.5 * sensor.exposure_s / self.duration  # half the exposure, normalised time
        ends = self.flight.pose(np.array([u - half, u + half]), self.frames)
        blur = self.renderer.blur_pixels(ends[0], ends[1])
        offsets = self.renderer.subframes(blur, sensor.max_subframes)
        sub = self.flight.pose(u + offsets * 2 * half, self.frames)
        image = self.renderer.radiance(sub).mean(axis=0)
        if self._vignette is not None:
            image = image * self._vignette
        return expose(image, float(self.gain[s]), sensor, np.random.default_rng([self.seed, 5, s]))

    def images(self) -> Iterator[np.ndarray]:
        """The delivered uint8 [H, W] frames in order (a duplicate is the previous buffer)."""
        last: np.ndarray | None = None
        for d in self.delivered:
            if d.shows != d.source and last is not None:
                yield last
                continue
            frame = self.render_source(d.source)
            if d.tear_row is not None:
                frame = tear(frame, d.tear_row, str(d.tear_kind), d.tear_shift)
            last = frame
            yield frame

    def document(self, fmt: str = "mp4") -> dict[str, object]:
        """The ground-truth document (module docstring) for output format ``fmt``."""
        sensor, d = self.capture.sensor, self.delivered
        files = formats.frame_files(fmt, [x.source for x in d], FPS) if fmt != "mp4" else None
        frames = []
        for k, x in enumerate(d):
            rec: dict[str, object] = {
                "index": k,
                "timestamp": x.shows / FPS,
                "c2w": self.poses[x.shows].tolist(),
                "source_frame": x.source,
                "frame_id": x.source % 256,
                "frame_timestamp": int(formats.ticks(x.source / FPS)),
            }
            if x.shows != x.source:
                rec["shows"] = x.shows
            if x.tear_row is not None:
                rec["tear"] = {"row": x.tear_row, "kind": x.tear_kind, "shift": x.tear_shift}
            if files:
                rec["file"] = files[k]
            frames.append(rec)
        got = {x.source for x in d}
        return {
            "fps": FPS,
            "intrinsics": intrinsics_record(sensor),
            "frames": frames,
            "stream": {
                "source_frames": self.frames,
                "delivered": len(d),
                "dropped": [s for s in range(self.frames) if s not in got],
                "duplicated": [x.source for x in d if x.shows != x.source],
                "torn": [x.source for x in d if x.tear_row is not None and x.shows == x.source],
                "link": dataclasses.asdict(self.capture.link),
            },
            "sensor": {"name": self.capture.sensor_name, **sensor.describe()},
            "format": fmt,
            "scene": {
                **self.scene.description,
                "frames": self.frames,
                "exposure_s": sensor.exposure_s,
                "noise": {"read_dn": sensor.read_noise, "shot_dn_per_dn": sensor.shot_noise},
                "exposure_gain_range": [float(self.gain.min()), float(self.gain.max())],
            },
        }

    def onboard_states(self) -> dict[str, np.ndarray]:
        """The onboard estimate (``times`` s, ``position`` m, ``velocity`` m/s, ``quaternion``
        xyzw, ``yaw_error`` rad) from just before the first frame to the last."""
        noise = self.capture.state_noise
        times = telemetry.state_times(-0.05, (self.frames - 1) / FPS, noise, self.seed)
        body = telemetry.body_poses(self.pose_at(times))
        dt = 1e-3
        velocity = (self.pose_at(times + dt)[:, :3, 3] - self.pose_at(times - dt)[:, :3, 3]) / (
            2 * dt
        )
        return {"times": times, **telemetry.estimate(times, body, velocity, noise, self.seed)}


def render_flight(
    scene_name: str, frames: int, seed: int, capture: Capture | None = None
) -> tuple[Iterator[np.ndarray], dict[str, object]]:
    """Delivered frames (uint8 [H, W], rendered lazily in order) and the ground-truth document
    of an mp4 capture."""
    sim = SimulatedFlight(scene_name, frames, seed, capture or Capture(sensor_name="clean"))
    return sim.images(), sim.document()


def simulate(
    scene_name: str,
    output: str | Path,
    frames: int = 600,
    seed: int = 0,
    codec: str = "ffv1",
    progress: bool = True,
    capture: Capture | None = None,
    fmt: str = "mp4",
    part: tuple[float, float] = (0.0, 1.0),
    scene_seed: int | None = None,
) -> tuple[Path, Path]:
    """Render a flight to ``output``: a video (``fmt`` mp4; ground truth beside it with suffix
    ``.json``) or a capture folder (nanocockpit, pulp-dronet; ``flight.json`` inside).

    ``part`` and ``scene_seed``: a swarm's drone (:class:`SimulatedFlight`).

    Returns:
        (video or folder, ground-truth JSON path); both appear only when complete.
    """
    from dronecap.progress import progress_bar

    if fmt not in formats.FORMATS:
        raise InputError(f"unknown format {fmt!r}, expected one of {', '.join(formats.FORMATS)}")
    capture = capture or Capture(sensor_name="clean")
    quality = capture.sensor.jpeg_quality
    if fmt == "pulp-dronet":  # the JPEG file is the compression: encode once, at the file
        quality = quality or formats.PULP_JPEG_QUALITY
        capture = dataclasses.replace(
            capture, sensor=dataclasses.replace(capture.sensor, jpeg_quality=0)
        )
    sim = SimulatedFlight(scene_name, frames, seed, capture, part, scene_seed)
    output = Path(output)
    doc = sim.document(fmt)
    doc["sensor"]["jpeg_quality"] = quality  # type: ignore[index]
    bar = progress_bar(
        sim.images(),
        total=len(sim.delivered),
        unit="frame",
        desc="render",
        disable=None if progress else True,
        leave=False,
    )
    if fmt == "mp4":
        doc["scene"]["video"] = output.name  # type: ignore[index]
        doc["scene"]["codec"] = codec  # type: ignore[index]
        return formats.write_video(output, bar, FPS, codec, doc)
    states = sim.onboard_states()
    noise = sim.capture.state_noise
    doc["body_from_camera"] = telemetry.BODY_FROM_CAMERA.tolist()
    doc["telemetry"] = {
        "file": "metadata.csv" if fmt == "nanocockpit" else "state.csv",
        "rows": len(states["times"]) if fmt == "pulp-dronet" else len(sim.delivered),
        "noise": dataclasses.asdict(noise),
        "final_yaw_error_deg": float(np.degrees(states["yaw_error"][-1])),
    }
    return formats.write_folder(output, fmt, bar, doc, states, quality)


__all__ = ["Capture", "Delivered", "capture_preset", "SimulatedFlight", "render_flight", "simulate"]
