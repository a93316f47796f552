"""Dropping the samples a ray cannot show before the training pass (Instant-NGP's compaction).

Once the field has surfaces, most marched samples of a ray lie behind the first opaque one:
their transmittance is ~0, so their weight and every gradient through them are ~0, yet the
training pass (both MLPs, their backward, the hash table's scatter) would pay for each. A pass
without autograd (hash encoding and density MLP) finds them; the training pass then runs on the
samples in front and reuses their encodings (only the table's backward runs for them again).
On lego after 1000 steps 54 % of the marched samples have transmittance < 1e-4 (2000 steps:
58 %); early in training, while the field is fog, nearly none do, and on real Himax footage
(test_23, 10k steps) 0.8 % do over the whole run: there the pre-pass (~5 % of a step) is
all cost (10k steps 414 s against 386 s without it). So it runs only while it pays
(:func:`due`): when its last measurement dropped at least :data:`MIN_DROPPED` of the samples,
and every :data:`PROBE_EVERY` steps to measure again.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from .batch import RayBatch, whole_rays
from .field import Field
from .marching import Samples
from .volrend import packed_weights

MIN_DROPPED = 0.1  # the pre-pass costs ~5 % of a step: worth it above ~8 % of samples dropped
PROBE_EVERY = 16  # steps between measurements while compaction does not pay
# A step's batch counts the samples trained on (as Instant-NGP's does), so it marches more rays
# while compaction drops samples; the marched samples of a step are capped at this many batches
MARCH_CAP = 4


def due(step: int, dropped: float) -> bool:
    """Whether step ``step`` runs the pre-pass, given the share of samples it ``dropped`` when
    it last ran (1.0 before it ever ran)."""
    return dropped >= MIN_DROPPED or step % PROBE_EVERY == 0


def visible(
    s: Samples, origins: torch.Tensor, dirs: torch.Tensor, field: Field, min_transmittance: float
) -> Samples:
    """The samples of ``s`` with transmittance above ``min_transmittance`` before them, with
    their hash encodings (``encoded``) and unit-cube midpoints (``unit``) for the training pass.

    Args:
        s: packed samples of R rays (ordered by ray).
        origins, dirs: [R, 3] the rays (scene units, unit directions).
        field: the model (its encoding and density MLP, without autograd).
        min_transmittance: in [0, 1); 0 returns ``s`` as it is (nothing computed).

    Returns:
        the kept samples, packed by ray (``counts`` [R] renumbered; ``t_resume`` dropped). A
        ray's kept samples are a prefix of its samples (transmittance never rises along a
        ray), so rendering them gives the same colour up to the light behind the cut
        (< ``min_transmittance`` of it).
    """
    return visible_in_batch(s, origins, dirs, field, min_transmittance, 0)[0]


@torch.no_grad()
def visible_in_batch(
    s: Samples, origins: torch.Tensor, dirs: torch.Tensor, field: Field, min_transmittance: float,
    batch: int,
) -> tuple[Samples, int]:  # fmt: skip
    """:func:`visible`, and the count of samples it keeps; where the fused pre-pass runs and
    ``batch`` > 0, only the first whole rays whose kept samples fit in ``batch`` (what
    :func:`.batch.whole_rays` would then keep; ``counts`` [R'] for those R' rays), the count
    still before that cut."""
    if min_transmittance <= 0:
        return s, s.n
    ri = s.ray_indices
    v = field.visible_samples(origins, dirs, (s.t_starts, s.t_ends, ri), min_transmittance, batch)
    if v is not None:  # the same samples, in one C++ call
        return Samples(*v[:4], encoded=v.encoded, unit=v.unit), v.found  # ray_indices .. counts
    points = s.midpoints(origins, dirs)
    sigma, encoded = field.density_and_encoding(points)
    _, trans = packed_weights(sigma * (s.t_ends - s.t_starts), ri, s.counts.numel())
    keep = (trans > min_transmittance).nonzero().squeeze(1)
    encoded, unit = encoded[keep], field.unit(points[keep])
    ri = ri[keep]
    counts = torch.bincount(ri, minlength=s.counts.numel())
    kept = Samples(ri, s.t_starts[keep], s.t_ends[keep], counts, encoded=encoded, unit=unit)
    return kept, kept.n


@dataclass
class Tally:
    """A run's compaction: samples marched and trained on over the run, and the share the last
    pre-pass dropped (1.0 before any, so the first step measures)."""

    marched: int = 0
    trained: int = 0
    dropped: float = 1.0

    def compact(
        self, step: int, rays: RayBatch, s: Samples, field: Field, thresh: float, batch: int
    ) -> tuple[RayBatch, Samples]:
        """The rays of step ``step`` and their samples to train on: the :func:`visible` ones
        when :func:`due` (``thresh`` > 0), else ``s``, of the first whole rays holding at
        most ``batch`` of them; counted. Marched counts what the pre-pass ran on (all of
        ``s``) or, without one, the samples kept: rays cut off by the batch were not worked on
        beyond marching, so a run where compaction never pays counts marched == trained."""
        kept, prepass = s, thresh > 0 and due(step, self.dropped)
        if prepass:  # the kernel cuts the batch itself (no tensor ops for it here)
            kept, found = visible_in_batch(s, rays.origins, rays.dirs, field, thresh, batch)
            self.dropped = 1.0 - found / max(s.n, 1)
        rays, kept = whole_rays(rays, kept, batch)
        self.marched += s.n if prepass else kept.n
        self.trained += kept.n
        return rays, kept

    def counts(self, allowed: torch.Tensor | None) -> dict[str, float]:
        """{"marched", "trained"}: samples over the run; "hull_fraction": the share of the
        occupancy cells ``allowed`` (the visual hull; None: 1.0)."""
        hull = 1.0 if allowed is None else float(allowed.float().mean())
        return {"marched": self.marched, "trained": self.trained, "hull_fraction": hull}
