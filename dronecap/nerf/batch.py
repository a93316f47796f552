"""The rays of one training step: random pixels of a few random training images.

:func:`draw_rays` picks ``images_per_step`` training images, then random pixels of them, and
returns their rays through the camera model, their target colours (composited on a random
background when the images have alpha) and what the photometric model needs (frame, radius).
The pixels come from a splitmix64 stream seeded by one number off the trainer's generator
(:func:`.draws.pixel_draws`), which the C++ kernel and torch ops reproduce bit for bit.
"""

from __future__ import annotations

import functools
from typing import NamedTuple

import torch

from dronecap.camera import Camera

from .backend import kernel
from .draws import pixel_draws, seed_from
from .kernel_args import f32
from .marching import Samples
from .photometric import corner_distance_sq, normalized_radius
from .rays import direction_tables, frame_rays


class RayBatch(NamedTuple):
    """The rays of one step: where they start and go, what their pixels saw, where they came
    from (for the camera's photometric model)."""

    origins: torch.Tensor  # [R, 3] scene units
    dirs: torch.Tensor  # [R, 3] unit directions
    target: torch.Tensor  # [R, C] pixel colour in [0, 1] (composited on ``bg`` with alpha)
    bg: torch.Tensor  # [R, C] background the rendered colour is composited on
    frame: torch.Tensor  # [R] int64 training-frame index
    radius: torch.Tensor  # [R] pixel distance from the principal point (nerf.photometric)

    def rows(self, a: int, b: int) -> RayBatch:
        """Rays ``a`` to ``b - 1`` (views, no copy; the batch itself when that is all of it)."""
        if a == 0 and b >= self.origins.shape[0]:
            return self
        return RayBatch(*(t[a:b] for t in self))


def draw_rays(
    images: torch.Tensor,
    alpha: torch.Tensor | None,
    poses: torch.Tensor,
    cameras: tuple[Camera, ...],
    camera_index: torch.Tensor,
    background: tuple[float, ...],
    images_per_step: int,
    n_rays: int,
    generator: torch.Generator,
    backend: str = "auto",
) -> RayBatch:
    """``n_rays`` random pixels of ``images_per_step`` random frames of ``images``.

    Args:
        images: uint8 [N, H, W, C] training frames.
        alpha: uint8 [N, H, W] or None.
        poses: float32 [N, 4, 4] camera-to-world.
        cameras: the table of cameras (lens models included); ``camera_index`` (int64 [N]) picks
            each frame's.
        background: [C] colour in [0, 1] for frames without alpha.
        backend: the marching kernel's backend (``nerf.backend``): on the CPU with the C++
            kernel, one call draws the pixels and casts their rays (~0.1 ms of tensor ops less
            per lego step); else :func:`.draws.pixel_draws` and torch ops. Both draw the same pixels
            from one number off ``generator``.
    """
    dev = images.device
    n_img, h, w, c = images.shape
    k = min(images_per_step, n_img)
    seed = seed_from(generator)
    uint8 = images.dtype == torch.uint8 and (alpha is None or alpha.dtype == torch.uint8)
    ext = kernel("march", backend) if dev.type == "cpu" and uint8 else None
    if ext is None:
        which, u, v, bg = pixel_draws(seed, n_img, k, n_rays, (h, w, c), alpha is not None)
        if alpha is None:
            bg = torch.as_tensor(background, dtype=torch.float32).expand(n_rays, c)
        which, u, v, bg = (t.to(dev) for t in (which, u, v, bg))
        return _gather(images, alpha, poses, cameras, camera_index, which, u, v, bg)
    cam = cameras[0]
    origins, dirs, target, radius, which, bg = ext.draw_random(
        images.contiguous(),
        _NO_ALPHA if alpha is None else alpha.contiguous(),
        f32(poses),
        direction_tables(cameras),
        camera_index.contiguous(),
        seed, n_rays, k, _background(tuple(background)),
        float(cam.cx), float(cam.cy), corner_distance_sq(cam),
    )  # fmt: skip
    return RayBatch(origins, dirs, target, bg, which, radius)


_NO_ALPHA = torch.zeros(0, dtype=torch.uint8)


@functools.lru_cache(maxsize=8)
def _background(colour: tuple[float, ...]) -> torch.Tensor:
    """A fixed background colour as the kernel takes it (float32 [C], made once)."""
    return torch.tensor(colour, dtype=torch.float32)


def _gather(images, alpha, poses, cameras, camera_index, which, u, v, bg) -> RayBatch:
    """The PyTorch reference of the kernel's ``draw``: the rays and targets of pixels
    ``(which, v, u)`` [R] (the arguments of :func:`draw_rays`; ``bg`` [R, C])."""
    n_img, h, w, c = images.shape
    origins, dirs = frame_rays(poses[which], cameras, camera_index[which], u, v)
    pixel = (which * h + v) * w + u  # one flat gather instead of indexing [which, v, u]
    rgb = images.reshape(-1, c)[pixel].float() / 255.0
    if alpha is not None:
        a = (alpha.reshape(-1)[pixel].float() / 255.0).unsqueeze(-1)
        target = rgb * a + bg * (1.0 - a)
    else:
        target = rgb
    return RayBatch(origins, dirs, target, bg, which, normalized_radius(u, v, cameras[0]))


def whole_rays(rays: RayBatch, s: Samples, batch_samples: int) -> tuple[RayBatch, Samples]:
    """The first rays of a marched batch whose samples fit in ``batch_samples`` (whole rays,
    at least one); the rays beyond ``s``'s (its ``counts``, when the pre-pass cut the batch
    already) are dropped."""
    if s.n <= batch_samples:  # all of them (the common case: no cumulative sums)
        return rays.rows(0, s.counts.numel()), s
    cum = torch.cumsum(s.counts, 0)
    keep = max(int(torch.searchsorted(cum, torch.tensor(batch_samples), right=True)), 1)
    if keep < rays.origins.shape[0]:
        # samples are packed by ray: a prefix of rays owns a prefix of samples (views, no copy)
        n = int(cum[keep - 1])
        enc = None if s.encoded is None else s.encoded[:n]
        unit = None if s.unit is None else s.unit[:n]
        s = Samples(
            s.ray_indices[:n], s.t_starts[:n], s.t_ends[:n], s.counts[:keep], encoded=enc, unit=unit
        )
        rays = rays.rows(0, keep)
    return rays, s
