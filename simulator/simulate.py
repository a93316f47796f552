"""The simulate stage: render a nano-drone flight to a gray video plus ground truth JSON.

Ground truth (``<video stem>.json`` beside the video)::

    {"fps": 30,
     "intrinsics": {"fx", "fy", "cx", "cy", "width", "height"},   # pixels, centres at +0.5
     "frames": [{"index": i, "timestamp": t, "c2w": 4x4 nested list}, ...],
     "scene": {...}}

``c2w`` is camera-to-world in OpenCV camera axes (x right, y down, z forward), metres, at the
middle of frame i's exposure; ``index`` is the video frame number (what ingest stores as
``source_index``) and ``timestamp = index / fps`` seconds. The same seed gives the same video.
"""

from __future__ import annotations

import json
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from dronecap.errors import InputError
from dronecap.files import atomic_output
from dronecap.simulator.flights import Flight
from dronecap.simulator.render import Renderer, SimCamera
from dronecap.simulator.scenes import SCENES
from dronecap.simulator.video import write_gray_video

FPS = 30.0


def exposure_gain(u: np.ndarray, seed: int) -> np.ndarray:
    """Slow auto-exposure drift: gain [T] around 0.95, +-10 %, at normalised times ``u`` [T]."""
    p = np.random.default_rng([seed, 4]).uniform(0, 2 * np.pi, 2)
    return 0.95 * (
        1.0 + 0.07 * np.sin(2 * np.pi * 1.3 * u + p[0]) + 0.03 * np.sin(2 * np.pi * 3.1 * u + p[1])
    )


def render_flight(
    scene_name: str, frames: int, seed: int, camera: SimCamera | None = None
) -> tuple[Iterator[np.ndarray], dict[str, object]]:
    """Frames (uint8 [H, W], rendered lazily in order) and the ground-truth document."""
    if scene_name not in SCENES:
        raise InputError(f"unknown scene {scene_name!r}, expected one of {sorted(SCENES)}")
    if frames < 2:
        raise InputError(f"--frames must be at least 2, got {frames}")
    camera = camera or SimCamera()
    scene = SCENES[scene_name](seed)
    flight = Flight(scene_name, seed)
    renderer = Renderer(scene, camera)
    duration = frames / FPS
    u = np.arange(frames) / frames
    poses = flight.pose(u, frames)
    gain = exposure_gain(u, seed)
    half = 0.5 * camera.exposure / duration  # half the exposure in normalised time

    def generate() -> Iterator[np.ndarray]:
        for i in range(frames):
            ends = flight.pose(np.array([u[i] - half, u[i] + half]), frames)
            offsets = renderer.subframes(renderer.blur_pixels(ends[0], ends[1]))
            sub = flight.pose(u[i] + offsets * 2 * half, frames)
            image = renderer.radiance(sub).mean(axis=0)
            yield renderer.expose(image, float(gain[i]), np.random.default_rng([seed, 5, i]))

    doc = {
        "fps": FPS,
        "intrinsics": camera.intrinsics(),
        "frames": [
            {"index": i, "timestamp": i / FPS, "c2w": poses[i].tolist()} for i in range(frames)
        ],
        "scene": {
            **scene.description,
            "frames": frames,
            "exposure_s": camera.exposure,
            "noise": {"read_dn": camera.read_noise, "shot_dn_per_dn": camera.shot_noise},
            "exposure_gain_range": [float(gain.min()), float(gain.max())],
        },
    }
    return generate(), doc


def simulate(
    scene_name: str,
    video: str | Path,
    frames: int = 600,
    seed: int = 0,
    codec: str = "ffv1",
    progress: bool = True,
) -> tuple[Path, Path]:
    """Render a flight to ``video`` and its ground truth to ``video`` with suffix ``.json``.

    Returns:
        (video path, ground-truth JSON path); both are written atomically.
    """
    from dronecap.progress import progress_bar

    video = Path(video)
    gt_path = video.with_suffix(".json")
    images, doc = render_flight(scene_name, frames, seed)
    bar = progress_bar(
        images,
        total=frames,
        unit="frame",
        desc="render",
        disable=None if progress else True,
        leave=False,
    )
    write_gray_video(video, bar, FPS, codec)
    doc["scene"]["video"] = video.name  # type: ignore[index]
    doc["scene"]["codec"] = codec  # type: ignore[index]
    with atomic_output(gt_path) as tmp:
        tmp.write_text(json.dumps(doc))
    return video, gt_path
