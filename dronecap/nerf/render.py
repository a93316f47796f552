"""Rendering a trained model: rays through the field with early termination, and whole views.

Nothing here trains or knows the run folder: :class:`Volume` is what rendering needs of a model
(the field, its occupancy grid and bounds, the marching function and step), and both functions
are pure in it. Rays are cast through the stored camera model (:func:`nerf.rays.camera_rays`).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from dronecap.camera import Camera

from .field import Field
from .occupancy import GridState
from .rays import camera_rays, ray_aabb
from .volrend import accumulate, packed_weights

RENDER_RAYS = 1 << 15  # rays per chunk when rendering a view
RENDER_ROUND = 16  # samples per ray evaluated per round when rendering
RENDER_FIELD_CHUNK = 1 << 14  # samples per field call when rendering (activations stay in cache)
MIN_TRANSMITTANCE = 1e-3  # a ray stops once less than this much light passes
MIN_WEIGHT = 1e-4  # samples of smaller weight skip the colour MLP


@dataclass
class Volume:
    """What rendering needs of a model (all on one device).

    ``march`` is :func:`nerf.marching.march` or its C++ twin; ``step_size`` in scene units;
    ``aabb`` float32 [2, 3]; ``max_samples`` per ray.
    """

    field: Field
    grid: GridState
    aabb: Tensor
    step_size: float
    max_samples: int
    march: Callable


def _in_chunks(fn: Callable, *tensors: Tensor) -> list:
    """``fn`` applied to ``RENDER_FIELD_CHUNK`` rows of ``tensors`` at a time (all [N, ...]),
    so the MLP activations stay in cache; the list of results (empty for N = 0)."""
    chunks = (t.split(RENDER_FIELD_CHUNK) for t in tensors)
    return [fn(*rows) for rows in zip(*chunks, strict=True)]


@torch.no_grad()
def render_rays(
    vol: Volume,
    origins: Tensor,
    dirs: Tensor,
    background: Tensor,
    min_transmittance: float = MIN_TRANSMITTANCE,
    min_weight: float = MIN_WEIGHT,
) -> Tensor:
    """Colours [R, C] in [0, 1] of rays ``origins``/``dirs`` [R, 3] (no grad).

    Marches and evaluates ``RENDER_ROUND`` samples per ray per round and stops rays whose
    transmittance fell below ``min_transmittance`` (early termination: what lies behind an
    opaque surface is not evaluated); the colour MLP runs only for samples of weight above
    ``min_weight``. ``background`` is [C] or [R, C]; a model with a far field shows that
    instead (:mod:`nerf.far_field`: ``C_box + T_exit * far(d)``). Samples sit where an
    unlimited march would put them, so the result differs only by the dropped tail
    (< ``min_transmittance``) and the skipped weights (< ``min_weight`` each): on lego models,
    71-79 dB (PSNR) from the exact render (benchmarks/train_speed.py).
    """
    field = vol.field
    n, c, dev = origins.shape[0], field.channels, origins.device
    t_near, t_far, hit = ray_aabb(origins, dirs, vol.aabb, field.encoding.backend)
    dir_enc = field.dir_encoding(dirs)  # [R, 16]: once per ray, gathered per sample
    rgb = torch.zeros(n, c, device=dev)
    trans = torch.ones(n, device=dev)
    alive = hit.nonzero().squeeze(1)
    t0 = t_near.clone()
    while alive.numel():
        o, d, t_end, m = origins[alive], dirs[alive], t_far[alive], alive.numel()
        s = vol.march(
            o, d, t0[alive], t_end, vol.step_size, vol.grid, vol.aabb, vol.max_samples,
            max_kept=RENDER_ROUND,
        )  # fmt: skip
        t0[alive] = s.t_resume
        if s.n == 0:
            alive = alive[s.t_resume < t_end]
            continue
        ri, t_s, t_e = s.ray_indices, s.t_starts, s.t_ends
        pts = torch.addcmul(o[ri], d[ri], (0.5 * (t_s + t_e))[:, None])
        parts = _in_chunks(field.geometry, pts)
        sigmas, geo = torch.cat([p[0] for p in parts]), torch.cat([p[1] for p in parts])
        tau = sigmas * (t_e - t_s)
        tr_alive = trans[alive]
        w, _ = packed_weights(tau, ri, m)
        w = w * tr_alive[ri]
        use = (w > min_weight).nonzero().squeeze(1)  # colour only where it shows
        colors = torch.cat(
            _in_chunks(field.color_from_encoding, geo[use], dir_enc[alive[ri[use]]])
            or [geo.new_zeros(0, c)]
        )
        rgb.index_add_(0, alive[ri[use]], w[use, None] * colors)
        tr_alive = tr_alive * torch.exp(-accumulate(tau, ri, m))
        trans[alive] = tr_alive
        alive = alive[(tr_alive > min_transmittance) & (s.t_resume < t_end)]
    bg = background.expand(n, c) if background.ndim == 1 else background
    return (rgb + trans[:, None] * field.behind(dirs, bg)).clamp(0, 1)


@torch.no_grad()
def render_view(
    vol: Volume,
    c2w: np.ndarray,
    camera: Camera,
    background: tuple[float, ...],
    min_transmittance: float = MIN_TRANSMITTANCE,
    min_weight: float = MIN_WEIGHT,
) -> np.ndarray:
    """Render one view through ``camera`` (its lens model included).

    Args:
        vol: the model.
        c2w: [4, 4] camera-to-world (OpenCV axes).
        camera: intrinsics and distortion; the output has its width and height.
        background: C values in [0, 1].
        min_transmittance, min_weight: early-termination thresholds of :func:`render_rays`.

    Returns:
        float32 [H, W, C] in [0, 1].
    """
    vol.field.eval()
    dev = vol.aabb.device
    h, w = camera.height, camera.width
    bg = torch.as_tensor(background, dtype=torch.float32, device=dev)
    vv, uu = torch.meshgrid(torch.arange(h, device=dev), torch.arange(w, device=dev), indexing="ij")
    uu, vv = uu.reshape(-1), vv.reshape(-1)
    pose = torch.as_tensor(np.asarray(c2w), dtype=torch.float32, device=dev)
    out = []
    for a in range(0, h * w, RENDER_RAYS):
        origins, dirs = camera_rays(pose, camera, uu[a : a + RENDER_RAYS], vv[a : a + RENDER_RAYS])
        out.append(render_rays(vol, origins, dirs, bg, min_transmittance, min_weight))
    return torch.cat(out).reshape(h, w, -1).cpu().numpy().astype(np.float32)


def render_preview(
    vol: Volume,
    c2w: np.ndarray,
    camera: Camera,
    background: tuple[float, ...],
    scale: float = 0.5,
) -> np.ndarray:
    """A quick look at a view: :func:`render_view` through ``camera`` resized by ``scale``
    (same field of view; half resolution renders a quarter of the rays) -> float32
    [round(H * scale), round(W * scale), C]."""
    small = camera.scaled_to(
        max(1, round(camera.width * scale)), max(1, round(camera.height * scale))
    )
    return render_view(vol, c2w, small, background)
