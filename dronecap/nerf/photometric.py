"""The camera's photometric model learned while training: per-frame exposure and vignetting.

A real nano-drone camera shows the scene's radiance through two effects the field should not
learn as scene content:

- **exposure**: auto exposure scales every frame by its own gain. Each training frame ``i`` has
  a learned log-gain per channel ``l[i, c]`` (initially 0); a pixel of frame ``i`` is scaled by
  ``exp(l[i, c] - mean_j l[j, c])``. Subtracting the mean over frames fixes the gauge (a
  brighter scene with darker gains renders the same frames): the geometric mean gain is 1, so
  the scene keeps the average exposure of the training frames.
- **vignetting**: the lens darkens the image towards its corners, the same way in every frame
  of one camera: the factor ``1 + k1 r^2 + k2 r^4 + k3 r^6`` (``k`` learned, initially 0)
  over its largest value for r in [0, 1] (so it never brightens), with
  ``r`` the distance of the pixel centre from the principal point over that of the farthest
  image corner (0 at the principal point, 1 at the farthest corner).

Both multiply the rendered colour after compositing the background (the camera saw all of it)
and before the loss. Renders use the field alone (the scene's radiance at the reference
exposure, no vignetting). A test view is scored as the camera recorded it
(:meth:`Photometric.recorded`): the render times the learned vignetting of its lens and the
exposure of its moment, interpolated in capture time between the same drone's training frames
(auto exposure drifts smoothly; no test pixel is used). The parameters are the drone's own,
never part of the exchanged or costed network.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor, nn

from dronecap.camera import Camera

MAX_LOG_GAIN = 3.0  # |log-gain| limit per frame (gains within e^-3..e^3 = 0.05..20)
VIGNETTE_RANGE = (0.05, 2.0)  # the vignetting factor is clamped to this (positive, finite)
# Radii (evenly over [0, 1]) at which the falloff polynomial's largest value is taken: the factor
# is the polynomial over it, so no ring is brighter than 1. Left free, a model with a far field
# learned a bright ring (x 1.15 at r 0.8 on the simulated corridor, which has no vignetting)
# and rendered its walls that much darker (benchmarks/results/far_field.md, session 12).
PEAK_RADII = 33
VIGNETTE_TERMS = 3  # k1 r^2 + k2 r^4 + k3 r^6


def normalized_radius(u: Tensor, v: Tensor, camera: Camera) -> Tensor:
    """Distance of pixel centres from the principal point over that of the farthest corner.

    Args:
        u: [R] pixel columns (integers; the centre of column u is at u + 0.5 px).
        v: [R] pixel rows.
        camera: the frames' camera (principal point ``cx``, ``cy`` and size in pixels).

    Returns:
        float32 [R], 0 at the principal point and 1 at the farthest image corner.
    """
    du = u.float() + 0.5 - camera.cx
    dv = v.float() + 0.5 - camera.cy
    return torch.sqrt((du * du + dv * dv) / max(corner_distance_sq(camera), 1e-12))


def corner_distance_sq(camera: Camera) -> float:
    """Squared distance (px^2) from the principal point to the farthest image corner."""
    return max(
        (x - camera.cx) ** 2 + (y - camera.cy) ** 2
        for x in (0, camera.width)
        for y in (0, camera.height)
    )


class Photometric(nn.Module):
    """Per-frame exposure and one vignetting falloff (see the module docstring).

    Args:
        n_frames: training frames (rows of the log-gain table).
        channels: colour channels C.
        exposure: learn a gain per frame and channel.
        vignetting: learn the radial falloff.

    Parameters (absent when their part is off): ``log_gain`` [n_frames, C] (natural log of
    the gain, before centring) and ``vignette`` [3] (k1, k2, k3).
    """

    def __init__(self, n_frames: int, channels: int, exposure: bool, vignetting: bool) -> None:
        super().__init__()
        self.channels = channels
        self.log_gain = nn.Parameter(torch.zeros(n_frames, channels)) if exposure else None
        self.vignette = nn.Parameter(torch.zeros(VIGNETTE_TERMS)) if vignetting else None

    def identity(self) -> bool:
        """Whether the model learns nothing (its :meth:`forward` returns the colour itself)."""
        return self.log_gain is None and self.vignette is None

    def gains(self) -> Tensor:
        """Gains [n_frames, C] (factor of the linear colour): ``exp`` of the clamped log-gains
        minus their mean over frames, so their geometric mean is 1 per channel."""
        log_gain = self.log_gain.clamp(-MAX_LOG_GAIN, MAX_LOG_GAIN)
        return torch.exp(log_gain - log_gain.mean(0, keepdim=True))

    def falloff(self, radius: Tensor) -> Tensor:
        """Vignetting factor [R] at normalised radii [R] (:func:`normalized_radius`): the
        polynomial over its largest value on [0, 1] (1 at the centre unless a ring is
        brighter: a lens only darkens), clamped to :data:`VIGNETTE_RANGE`."""
        peak = self._polynomial(torch.linspace(0.0, 1.0, PEAK_RADII)).max()
        return (self._polynomial(radius) / peak).clamp(*VIGNETTE_RANGE)

    def _polynomial(self, radius: Tensor) -> Tensor:
        """``1 + k1 r^2 + k2 r^4 + k3 r^6`` [R] at radii [R]."""
        r2 = radius * radius
        return 1.0 + torch.stack([r2, r2 * r2, r2 * r2 * r2], -1) @ self.vignette

    def forward(self, color: Tensor, frame: Tensor, radius: Tensor) -> Tensor:
        """The colour the camera records of rendered colour ``color``.

        Args:
            color: [R, C] rendered colour in [0, 1] (background composited).
            frame: [R] int64 training-frame index of each ray.
            radius: [R] normalised radius of each ray's pixel (:func:`normalized_radius`).

        Returns:
            [R, C] ``color`` times the frame's gain and the vignetting factor (those that are
            learned; ``color`` itself when neither is).
        """
        if self.log_gain is not None:
            color = color * self.gains()[frame]
        if self.vignette is not None:
            color = color * self.falloff(radius).unsqueeze(-1)
        return color

    @torch.no_grad()
    def summary(self) -> dict[str, list | None]:
        """What was learned, JSON-able: {"gains": [n_frames][C] (applied gains) or None,
        "vignette": [k1, k2, k3] or None, "corner_falloff": factor at the farthest corner or
        None}."""
        learned = self.vignette is not None
        return {
            "gains": None if self.log_gain is None else self.gains().tolist(),
            "vignette": self.vignette.tolist() if learned else None,
            "corner_falloff": float(self.falloff(torch.ones(1))[0]) if learned else None,
        }

    def resize_frames(self, n_frames: int) -> bool:
        """Start over with ``n_frames`` gains of 1 when the table has another number of rows
        (a model continued on other frames); True when it did."""
        if self.log_gain is None or self.log_gain.shape[0] == n_frames:
            return False
        self.log_gain = nn.Parameter(self.log_gain.new_zeros(n_frames, self.channels))
        return True

    @torch.no_grad()
    def recorded(
        self,
        image: np.ndarray,
        camera: Camera,
        when: tuple[float, int] | None,
        frames: tuple[np.ndarray, np.ndarray] | None,
    ) -> np.ndarray:
        """What the camera recorded of a rendered view, clipped to [0, 1].

        Args:
            image: float32 [H, W, C] render (the scene at the reference exposure).
            camera: the view's camera (its principal point centres the vignetting).
            when: (capture time s, drone) of the view, or None (reference exposure).
            frames: (capture times s [N], drones [N]) of the training frames, in the order of
                the gain table's rows, or None (reference exposure).

        Returns:
            float32 [H, W, C]: ``image`` times the vignetting factor (when learned) and the
            view's gain (when exposure is learned and the view has training frames of its
            drone: the log-gain linearly interpolated in time, held at the first and last).
        """
        out = image.astype(np.float32)
        if self.vignette is not None:
            h, w = image.shape[:2]
            v, u = torch.meshgrid(torch.arange(h), torch.arange(w), indexing="ij")
            radius = normalized_radius(u.reshape(-1), v.reshape(-1), camera)
            out = out * self.falloff(radius).reshape(h, w, 1).numpy()
        if self.log_gain is not None and when is not None and frames is not None:
            times, drones = frames
            mine = np.flatnonzero(drones == when[1])
            if times.shape[0] == self.log_gain.shape[0] and mine.size:
                order = mine[np.argsort(times[mine], kind="stable")]
                log_gain = torch.log(self.gains()).numpy()[order]  # [M, C]
                at = [np.interp(when[0], times[order], g) for g in log_gain.T]  # [C]
                out = out * np.exp(np.asarray(at, np.float32))
        return np.clip(out, 0.0, 1.0)
