"""Smooth nano-drone trajectories for the simulated scenes.

A flight is defined over normalised time ``u`` in [0, 1], so ``--frames N`` renders the same
route at N frames (fewer frames = a faster flight with more motion per frame). It has:

- an *activity clock*: progress along the route slows to zero in two hovers (about 5% of the
  flight each) and everything that moves (position, yaw, height) follows this clock, so a
  hover is a real hover apart from a few millimetres of jitter;
- yaw sweeps of +-30 degrees (looking at the walls and the cones), lateral and height sway,
  a slight downward pitch, and a few short yaw twitches ("gusts") that blur a handful of frames.

A swarm's drone flies one ``part`` of the route (a range of the activity clock; the orbit's
route wraps around), so drones of one scene cover neighbouring, overlapping pieces of it.

``pose(u)`` returns camera-to-world matrices in OpenCV camera axes (x right, y down, z forward).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


def camera_to_world(
    position: np.ndarray, yaw: np.ndarray, pitch: np.ndarray, roll: np.ndarray
) -> np.ndarray:
    """Camera-to-world [T, 4, 4] for a camera at ``position`` [T, 3] (m, world z up).

    ``yaw`` [T] rotates the view about world z from +x towards +y, ``pitch`` [T] raises it,
    ``roll`` [T] turns the image clockwise about the optical axis; radians.
    """
    cy, sy, cp, sp = np.cos(yaw), np.sin(yaw), np.cos(pitch), np.sin(pitch)
    fwd = np.stack([cp * cy, cp * sy, sp], -1)
    right = np.stack([sy, -cy, 0 * yaw], -1)  # forward x world-up, normalised
    down = np.cross(fwd, right)
    cr, sr = np.cos(roll)[:, None], np.sin(roll)[:, None]
    right, down = cr * right + sr * down, -sr * right + cr * down
    m = np.zeros((len(yaw), 4, 4))
    m[:, :3, 0], m[:, :3, 1], m[:, :3, 2], m[:, :3, 3] = right, down, fwd, position
    m[:, 3, 3] = 1.0
    return m


def look_at(
    position: np.ndarray, target: np.ndarray, yaw_offset: np.ndarray | float = 0.0
) -> np.ndarray:
    """Camera-to-world [T, 4, 4] of cameras at ``position`` [T, 3] looking at ``target`` [3],
    then turned by ``yaw_offset`` (radians, [T] or scalar) about world z."""
    d = np.asarray(target)[None] - position
    yaw = np.arctan2(d[:, 1], d[:, 0]) + yaw_offset
    pitch = np.arctan2(d[:, 2], np.hypot(d[:, 0], d[:, 1]))
    return camera_to_world(position, yaw, pitch, np.zeros(len(position)))


@dataclass
class Flight:
    """A route over normalised time; build with :func:`corridor_flight` or :func:`orbit_flight`."""

    scene: str
    rng_seed: int
    part: tuple[float, float] = (0.0, 1.0)  # the piece of the route flown (route clock units)

    def __post_init__(self) -> None:
        rng = np.random.default_rng([self.rng_seed, 3])
        grid = np.linspace(0.0, 1.0, 4097)
        speed = np.ones_like(grid)
        for centre in (rng.uniform(0.25, 0.35), rng.uniform(0.6, 0.7)):  # two hovers
            speed *= 1.0 - np.exp(-(((grid - centre) / 0.025) ** 8))
        clock = np.concatenate([[0.0], np.cumsum((speed[1:] + speed[:-1]) / 2)])
        self._grid, self._clock = grid, clock / clock[-1]
        self._phase = rng.uniform(0, 2 * np.pi, 8)
        self._gusts = np.sort(rng.uniform(0.08, 0.92, 3))
        self._gust_sign = rng.choice([-1.0, 1.0], 3)

    def clock(self, u: np.ndarray) -> np.ndarray:
        """Activity clock [T] in [0, 1] at normalised times ``u`` [T] (flat during hovers)."""
        return np.interp(u, self._grid, self._clock)

    def pose(self, u: np.ndarray, frames: int) -> np.ndarray:
        """Camera-to-world [T, 4, 4] at normalised times ``u`` [T] of a ``frames``-frame flight."""
        u = np.atleast_1d(np.asarray(u, float))
        a, b = self.part
        s, ph = a + (b - a) * self.clock(u), self._phase
        seconds = u * frames / 30.0
        jitter = np.stack(
            [
                0.003 * np.sin(2 * np.pi * f * seconds + p)
                for f, p in zip((1.3, 1.7, 2.3), ph[5:], strict=True)
            ],
            -1,
        )
        gust = sum(
            g * np.radians(7.0) * np.exp(-(((seconds - c * frames / 30.0) / 0.06) ** 2))
            for c, g in zip(self._gusts, self._gust_sign, strict=True)
        )
        if self.scene == "orbit":
            angle = 2 * np.pi * s + ph[0]
            radius = 1.7 + 0.15 * np.sin(2 * np.pi * 2 * s + ph[1])
            pos = np.stack(
                [
                    radius * np.cos(angle),
                    radius * np.sin(angle),
                    0.9 + 0.2 * np.sin(2 * np.pi * 1.5 * s + ph[2]),
                ],
                -1,
            )
            return look_at(pos + jitter, np.array([0.0, 0.0, 0.3]), gust)
        x = -0.3 + 3.1 * s
        y = 0.25 * np.sin(2 * np.pi * 1.3 * s + ph[0])
        z = 1.0 + 0.15 * np.sin(2 * np.pi * 2.1 * s + ph[1])
        yaw = np.radians(22.0) * np.sin(2 * np.pi * 2.2 * s + ph[2]) + np.radians(8.0) * np.sin(
            2 * np.pi * 5.0 * s + ph[3]
        )
        pitch = np.radians(-10.0 + 3.0 * np.sin(2 * np.pi * 1.7 * s + ph[4]))
        roll = np.radians(2.0) * np.sin(2 * np.pi * 3.1 * s + ph[5])
        return camera_to_world(np.stack([x, y, z], -1) + jitter, yaw + gust, pitch, roll)
