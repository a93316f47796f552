"""Onboard state estimates of the simulated drone, as a Crazyflie's estimator reports them.

The telemetry pose is the drone BODY in a z-up world (body x forward, y left, z up); the camera
looks along body +x (see the telemetry contract): ``c2w = [R_world_from_body @ BODY_FROM_CAMERA,
p]``, camera at the body origin. The estimator (flow deck + ToF height + IMU) is modelled as

- horizontal odometry with a scale error ``scale`` and a heading that drifts at ``yaw_drift``
  (degrees per minute): the horizontal track is scaled and turned about the start point;
- a random walk of ``walk`` mm per sqrt(second) on x and y (z comes from the height sensor:
  white noise only);
- white noise of ``position`` mm on each axis and ``angle`` degrees on each rotation axis
  (roll and pitch are observed from gravity and do not drift);
- velocity = the estimate's motion (true velocity through the same scale and heading) plus
  white noise of ``velocity`` mm/s;
- state rows at ``rate_hz`` with timestamps jittered by ``jitter_us`` microseconds.

All defaults are realistic levels for a flow-deck Crazyflie indoors.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

# camera axes in body coordinates (columns): cam_x = -body_y, cam_y = -body_z, cam_z = body_x
BODY_FROM_CAMERA = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])


@dataclass(frozen=True)
class StateNoise:
    """Errors of the onboard estimate (units in the names; see the module docstring)."""

    position_mm: float = 5.0
    angle_deg: float = 0.5
    velocity_mm_s: float = 20.0
    scale: float = 0.01  # relative horizontal scale error of the odometry
    yaw_drift_deg_min: float = 2.0
    walk_mm_sqrt_s: float = 3.0
    rate_hz: float = 100.0
    jitter_us: float = 300.0

    def problems(self) -> list[str]:
        """Out-of-range values (negative errors, a scale error beyond 50 %, a rate outside
        1-1000 Hz, jitter beyond a third of the state period)."""
        out = [
            f"{k} must be >= 0, got {v}"
            for k, v in asdict(self).items()
            if k not in ("scale", "rate_hz") and not v >= 0
        ]
        if not abs(self.scale) <= 0.5:
            out.append(f"odometry scale error must be within +-0.5, got {self.scale}")
        if not 1 <= self.rate_hz <= 1000:
            out.append(f"state rate must be 1-1000 Hz, got {self.rate_hz}")
        elif not self.jitter_us * 3 <= 1e6 / self.rate_hz:
            out.append("state timestamp jitter must be under a third of the state period")
        return out


def body_poses(c2w: np.ndarray) -> np.ndarray:
    """Body-to-world [T, 4, 4] of camera-to-world poses ``c2w`` [T, 4, 4] (camera at the body
    origin)."""
    out = np.array(c2w, float, copy=True)
    out[:, :3, :3] = c2w[:, :3, :3] @ BODY_FROM_CAMERA.T
    return out


def state_times(start_s: float, end_s: float, noise: StateNoise, seed: int) -> np.ndarray:
    """Timestamps (s) of the state rows covering [start, end]: ``rate_hz`` with jitter, strictly
    increasing. float64 [S]."""
    period = 1.0 / noise.rate_hz
    t = np.arange(start_s, end_s + period, period)
    jitter = np.random.default_rng([seed, 8]).normal(0.0, noise.jitter_us * 1e-6, len(t))
    return t + np.clip(jitter, -period / 3, period / 3)


def estimate(
    times: np.ndarray, body: np.ndarray, velocity: np.ndarray, noise: StateNoise, seed: int
) -> dict[str, np.ndarray]:
    """Onboard estimates at ``times`` [S] (s) of the true body poses ``body`` [S, 4, 4] (m) and
    velocities ``velocity`` [S, 3] (m/s).

    Returns:
        ``position`` [S, 3] m, ``velocity`` [S, 3] m/s, ``quaternion`` [S, 4] (x, y, z, w,
        Hamilton, body-to-world) and ``yaw_error`` [S] rad (the heading drift at each row).
    """
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng([seed, 9])
    n = len(times)
    yaw = np.radians(noise.yaw_drift_deg_min) / 60.0 * (times - times[0])
    drift = Rotation.from_rotvec(yaw[:, None] * [0.0, 0.0, 1.0]).as_matrix()  # [S, 3, 3]
    p0 = body[0, :3, 3]
    rel = body[:, :3, 3] - p0
    horiz = np.einsum("sij,sj->si", drift, rel * [1 + noise.scale, 1 + noise.scale, 0.0])
    pos = p0 + horiz + rel * [0.0, 0.0, 1.0]
    dt = np.diff(times, prepend=times[0])
    walk = np.cumsum(rng.standard_normal((n, 2)) * np.sqrt(dt)[:, None], 0)
    pos[:, :2] += walk * noise.walk_mm_sqrt_s * 1e-3
    pos += rng.normal(0.0, noise.position_mm * 1e-3, (n, 3))
    vel = np.einsum("sij,sj->si", drift, velocity * [1 + noise.scale, 1 + noise.scale, 1.0])
    vel += rng.normal(0.0, noise.velocity_mm_s * 1e-3, (n, 3))
    wobble = Rotation.from_rotvec(rng.normal(0.0, np.radians(noise.angle_deg), (n, 3)))
    att = Rotation.from_matrix(drift) * Rotation.from_matrix(body[:, :3, :3]) * wobble
    return {"position": pos, "velocity": vel, "quaternion": att.as_quat(), "yaw_error": yaw}
