"""Ray marching through the occupancy grid into packed samples (pure PyTorch reference).

Samples are packed: one flat list ordered by ray, with ``ray_indices`` naming each sample's ray.
A ray's candidate samples sit at ``t_near + (k + offset) * step`` inside ``[t_near, t_far)``;
those in empty cells are dropped. Only points inside the AABB are ever produced.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass

import torch
from torch import Tensor

from .occupancy import GridState, occupied_at


@dataclass
class Samples:
    """Packed samples of ``n_rays`` rays (S samples in total, ordered by ray).

    ray_indices: int64 [S]; t_starts, t_ends: float32 [S] (scene units along unit directions);
    counts: int64 [n_rays] samples per ray; t_resume: float32 [n_rays] where a further march
    of the ray continues (``t_near + e * step``, ``e`` the candidates examined; >= t_far when
    the ray is done), or None when not computed; encoded: float32 [S, L * F] the hash encoding
    of each sample's midpoint when :mod:`.compaction` computed it (no autograd), else None;
    unit: float32 [S, 3] those midpoints in the unit cube of the field's box, the coordinates
    ``encoded`` encodes (set with it).
    """

    ray_indices: Tensor
    t_starts: Tensor
    t_ends: Tensor
    counts: Tensor
    t_resume: Tensor | None = None
    encoded: Tensor | None = None
    unit: Tensor | None = None

    @property
    def n(self) -> int:
        """Total samples S."""
        return int(self.ray_indices.numel())

    def midpoints(self, origins: Tensor, dirs: Tensor) -> Tensor:
        """Each sample's midpoint [S, 3] on its ray (``origins``, ``dirs``: [R, 3])."""
        ri = self.ray_indices
        return torch.addcmul(origins[ri], dirs[ri], (0.5 * (self.t_starts + self.t_ends))[:, None])


def march(
    origins: Tensor,
    dirs: Tensor,
    t_near: Tensor,
    t_far: Tensor,
    step: float,
    grid: GridState | None,
    aabb: Tensor,
    max_samples: int,
    offsets: Tensor | None = None,
    max_kept: int = 0,
    chunk: int = 1 << 21,
) -> Samples:
    """March rays and keep the samples in occupied cells.

    Args:
        origins, dirs: [R, 3] rays (unit directions, scene units).
        t_near, t_far: [R] the ray's segment inside the AABB (t_far <= t_near: no samples).
        step: marching step in scene units (> 0).
        grid: occupancy state, or None to keep every sample.
        aabb: [2, 3] bounds of the grid.
        max_samples: at most this many candidates per ray.
        offsets: [R] position of the first sample within its step, in [0, 1) (training
            jitter); None puts samples at step midpoints (0.5).
        max_kept: > 0: a ray stops at this many kept samples (0: no limit); see ``t_resume``.
        chunk: candidates processed at once (bounds memory).

    Returns:
        :class:`Samples` with t_starts/t_ends clipped to [t_near, t_far], and t_resume.
    """
    if not step > 0:
        raise ValueError(f"marching step must be positive, got {step}")
    r = origins.shape[0]
    dev = origins.device
    length = (t_far - t_near).clamp_min(0.0)
    n_cand = torch.ceil(length / step).clamp(0, max_samples).long()
    off = torch.full((r,), 0.5, device=dev) if offsets is None else offsets
    # a jittered first sample may fall past t_far: drop those candidates below
    ray_ids, ts, ks = [], [], []
    ends = torch.cumsum(n_cand, 0)
    total = int(ends[-1]) if r else 0
    ray_all = torch.repeat_interleave(torch.arange(r, device=dev), n_cand)
    first = ends - n_cand
    for s in range(0, total, chunk):
        ri = ray_all[s : s + chunk]
        k = torch.arange(s, min(s + chunk, total), device=dev) - first[ri]
        t = t_near[ri] + (k.float() + off[ri]) * step
        keep = t < t_far[ri]
        if grid is not None:
            pts = origins[ri] + dirs[ri] * t.unsqueeze(-1)
            keep &= occupied_at(grid, pts, aabb)
        ray_ids.append(ri[keep])
        ts.append(t[keep])
        ks.append(k[keep])
    ray_indices = torch.cat(ray_ids) if ray_ids else torch.zeros(0, dtype=torch.long, device=dev)
    t_mid = torch.cat(ts) if ts else torch.zeros(0, device=dev)
    k_kept = torch.cat(ks) if ks else torch.zeros(0, dtype=torch.long, device=dev)
    examined = n_cand.clone()
    if max_kept > 0 and ray_indices.numel():
        counts = torch.bincount(ray_indices, minlength=r)
        rank = (
            torch.arange(ray_indices.numel(), device=dev)
            - (torch.cumsum(counts, 0) - counts)[ray_indices]
        )
        last = rank == max_kept - 1  # a ray's max_kept-th kept sample: it stops there
        examined[ray_indices[last]] = k_kept[last] + 1
        below = rank < max_kept
        ray_indices, t_mid = ray_indices[below], t_mid[below]
    t_resume = t_near + examined.float() * step
    half = 0.5 * step
    t_starts = torch.maximum(t_mid - half, t_near[ray_indices])
    t_ends = torch.minimum(t_mid + half, t_far[ray_indices])
    counts = torch.bincount(ray_indices, minlength=r)
    return Samples(ray_indices, t_starts, t_ends, counts, t_resume)


def tiles(s: Samples, tile_samples: int) -> Iterator[tuple[int, int, Samples]]:
    """Runs of whole rays holding about ``tile_samples`` samples each, in order.

    Yields:
        (first ray, one past the last ray, the run's samples with ray indices from 0).
    """
    n_rays = s.counts.shape[0]
    if s.n <= tile_samples:  # one tile (the default batch): no bounds to find
        yield 0, n_rays, s
        return
    start = torch.cumsum(s.counts, 0) - s.counts  # first sample of each ray
    tile_of_ray = torch.div(start, max(tile_samples, 1), rounding_mode="floor")
    bounds = torch.searchsorted(tile_of_ray, torch.unique(tile_of_ray)).tolist() + [n_rays]
    sample_bounds = start.tolist() + [s.n]
    for a, b in zip(bounds[:-1], bounds[1:], strict=True):
        sa, sb = sample_bounds[a], sample_bounds[b]
        enc = None if s.encoded is None else s.encoded[sa:sb]
        unit = None if s.unit is None else s.unit[sa:sb]
        ri, t0, t1 = s.ray_indices[sa:sb] - a, s.t_starts[sa:sb], s.t_ends[sa:sb]
        yield a, b, Samples(ri, t0, t1, s.counts[a:b], encoded=enc, unit=unit)
