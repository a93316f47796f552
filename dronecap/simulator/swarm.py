"""A swarm: N drones flying neighbouring, overlapping parts of one scene, each with its own camera.

Every drone flies its own piece of the scene's route (:func:`drone_part`: the corridor's length or
the orbit's circle cut into N pieces that overlap their neighbours by ``overlap`` of a piece),
through its own camera (:func:`drone_capture`: focal length, principal point, distortion,
vignetting and exposure drawn around the sensor's values within a few percent), with its own
sensor noise, exposure drift, link losses and onboard state drift (its own seed,
:func:`drone_seed`). The scene and the world frame are shared, so every drone's ground truth is in
one world frame.

Output folder (written under a temporary name, renamed when complete)::

    swarm/drone_0.mp4 + drone_0.json     (format mp4: a video and its ground truth per drone)
    swarm/drone_0/ ... flight.json       (nanocockpit, pulp-dronet: a capture folder per drone)
    swarm/swarm.json                     {"scene", "seed", "frames", "format", "sensor",
                                          "overlap", "drones": [{"name", "entry",
                                          "ground_truth", "seed", "part", "intrinsics"}, ...]}
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np

from dronecap.errors import InputError
from dronecap.files import atomic_output
from dronecap.simulator.simulate import Capture, intrinsics_record, simulate

MAX_DRONES = 16
OVERLAP = 0.3  # fraction of a drone's piece of the route shared with each neighbour
SPREAD = {"focal": 0.015, "principal": 0.01, "distortion": 0.05, "vignetting": 0.05}
SPREAD["exposure"] = 0.05  # relative spreads (standard deviations, clipped at 2 sigma)


def drone_part(d: int, drones: int, scene: str, overlap: float = OVERLAP) -> tuple[float, float]:
    """The piece of the route drone ``d`` of ``drones`` flies, in route-clock units:
    [d/N, (d+1)/N] widened by ``overlap`` of a piece on each side (the corridor's ends clip it;
    the orbit's circle wraps around)."""
    a, b = (d - overlap) / drones, (d + 1 + overlap) / drones
    if scene == "orbit":
        return a, b
    return max(0.0, a), min(1.0, b)


def drone_seed(seed: int, d: int) -> int:
    """The seed of drone ``d``'s noise, exposure, link and onboard state."""
    return int(np.random.SeedSequence([seed, 23, d]).generate_state(1)[0] % (2**31))


def drone_capture(capture: Capture, seed: int, d: int) -> Capture:
    """``capture`` with drone ``d``'s own camera: focal length, principal point, distortion,
    vignetting and exposure time drawn around the sensor's (relative spreads :data:`SPREAD`)."""
    rng = np.random.default_rng([seed, 29, d])

    def jitter(key: str, size: int | None = None) -> np.ndarray:
        return 1.0 + np.clip(rng.normal(0, SPREAD[key], size), -2 * SPREAD[key], 2 * SPREAD[key])

    sensor = capture.sensor
    lens = sensor.lens
    f = float(jitter("focal"))
    dx, dy = rng.normal(0, SPREAD["principal"], 2).clip(
        -2 * SPREAD["principal"], 2 * SPREAD["principal"]
    )
    lens = dataclasses.replace(
        lens,
        fx=lens.fx * f,
        fy=lens.fy * f,
        cx=lens.cx + float(dx) * lens.width,
        cy=lens.cy + float(dy) * lens.height,
        distortion=tuple(
            float(k * j)
            for k, j in zip(
                lens.distortion, jitter("distortion", len(lens.distortion)), strict=True
            )
        ),
    )
    sensor = dataclasses.replace(
        sensor,
        lens=lens,
        vignetting=min(0.95, sensor.vignetting * float(jitter("vignetting"))),
        exposure_s=sensor.exposure_s * float(jitter("exposure")),
    )
    return dataclasses.replace(capture, sensor=sensor)


def simulate_swarm(
    scene: str,
    output: str | Path,
    drones: int,
    frames: int = 600,
    seed: int = 0,
    codec: str = "ffv1",
    capture: Capture | None = None,
    fmt: str = "mp4",
    progress: bool = True,
) -> Path:
    """Render ``drones`` flights of ``frames`` source frames each through scene ``scene`` into
    the folder ``output`` (layout: module docstring); returns the folder.

    Raises:
        InputError: fewer than 2 or more than :data:`MAX_DRONES` drones, or an existing
            ``output`` that is not a folder.
    """
    if not 2 <= drones <= MAX_DRONES:
        raise InputError(f"drones must be 2-{MAX_DRONES}, got {drones}")
    output = Path(output)
    if output.exists() and not output.is_dir():
        raise InputError("exists and is not a folder", output)
    capture = capture or Capture(sensor_name="clean")
    records = []
    with atomic_output(output) as tmp:
        tmp.mkdir()
        for d in range(drones):
            name, own = f"drone_{d}", drone_capture(capture, seed, d)
            entry = tmp / (f"{name}.mp4" if fmt == "mp4" else name)
            part, s = drone_part(d, drones, scene), drone_seed(seed, d)
            _, gt = simulate(
                scene, entry, frames, s, codec, progress, own, fmt, part, scene_seed=seed
            )
            records.append(
                {
                    "name": name,
                    "entry": entry.name,
                    "ground_truth": str(gt.relative_to(tmp)),
                    "seed": s,
                    "part": list(part),
                    "intrinsics": intrinsics_record(own.sensor),
                }
            )
        doc = {
            "scene": scene,
            "seed": seed,
            "frames": frames,
            "format": fmt,
            "sensor": capture.sensor_name,
            "overlap": OVERLAP,
            "drones": records,
        }
        (tmp / "swarm.json").write_text(json.dumps(doc, indent=1))
    return output
