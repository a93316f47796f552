"""Compaction: samples behind an opaque surface leave the training pass, nothing else changes."""

import numpy as np
import pytest
import torch

from dronecap.nerf.backend import kernel
from dronecap.nerf.batch import RayBatch, whole_rays
from dronecap.nerf.compaction import visible, visible_in_batch
from dronecap.nerf.config import preset
from dronecap.nerf.field import Field
from dronecap.nerf.marching import Samples, march
from dronecap.nerf.rays import ray_aabb
from dronecap.nerf.volrend import render_packed

AABB = np.array([[-1.0, -1, -1], [1, 1, 1]])
BOX = torch.tensor(AABB, dtype=torch.float32)


def _field(backend: str = "auto") -> Field:
    torch.manual_seed(0)
    return Field(preset("test").replace(n_max=64), 3, AABB, backend=backend)


def _wall_field() -> Field:
    """A field whose density is huge for z > -0.4 (a wall across every ray along +z)."""
    f = _field()
    with torch.no_grad():
        f.density_mlp[-1].weight.zero_()
    f.encode = lambda p: torch.where(p[:, 2:] > -0.4, 1.0, 0.0).expand(-1, 2)  # type: ignore
    f.geometry_from_encoding = lambda e: (e[:, 0] * 1e4, e)  # type: ignore
    f.density_from_encoding = lambda e: e[:, 0] * 1e4  # type: ignore
    f.density_and_encoding = lambda p, keep_encoded=True: (  # type: ignore
        f.density_from_encoding(f.encode(p)),
        f.encode(p),
    )
    f.visible_samples = lambda *args: None  # type: ignore  # not the fused C++ pre-pass
    return f


def _rays(n: int = 6):
    g = torch.Generator().manual_seed(1)
    o = torch.cat([torch.rand(n, 2, generator=g) - 0.5, torch.full((n, 1), -3.0)], 1)
    d = torch.nn.functional.normalize(torch.tensor([[0.05, -0.03, 1.0]]).expand(n, 3), dim=-1)
    return o, d.contiguous()


def test_samples_behind_an_opaque_wall_are_dropped_and_the_rest_kept_in_order():
    o, d = _rays()
    tn, tf, _ = ray_aabb(o, d, BOX)
    s = march(o, d, tn, tf, 0.05, None, BOX, 1000)
    kept = visible(s, o, d, _wall_field(), 1e-4)
    mid = s.midpoints(o, d)
    for r in range(o.shape[0]):
        z_all = mid[s.ray_indices == r, 2]
        z_kept = kept.midpoints(o, d)[kept.ray_indices == r, 2]
        first_wall = int((z_all > -0.4).nonzero()[0])
        # a prefix: everything in front of the wall and the wall's first sample
        assert torch.equal(z_kept, z_all[: first_wall + 1])
    assert kept.counts.tolist() == torch.bincount(kept.ray_indices, minlength=6).tolist()
    assert kept.n < s.n / 2 and kept.encoded.shape == (kept.n, 2)
    assert visible(s, o, d, _wall_field(), 0.0) is s  # off: nothing computed


@pytest.mark.skipif(kernel("hashgrid", "auto") is None, reason="C++ hash-grid kernel unavailable")
def test_training_on_reused_encodings_gives_the_same_colour_and_gradients():
    """Nothing dropped (threshold 1e-30): the training pass with compaction's cached encodings
    renders and differentiates exactly as the pass that encodes again."""
    o, d = _rays()
    tn, tf, _ = ray_aabb(o, d, BOX)
    s = march(o, d, tn, tf, 0.05, None, BOX, 1000)
    grads, colors = [], []
    for cached in (False, True):
        f = _field()
        enc = visible(s, o, d, f, 1e-30).encoded if cached else None
        dir_enc = f.dir_encoding(d)

        def color_sigma(t0, t1, ri, f=f, enc=enc, dir_enc=dir_enc):
            sigma, geo = f.geometry(s.midpoints(o, d), enc)
            return f.color_from_encoding(geo, dir_enc[ri]), sigma

        out = render_packed(s.t_starts, s.t_ends, s.ray_indices, 6, color_sigma, torch.zeros(3))
        out.color.square().sum().backward()
        colors.append(out.color.detach())
        grads.append([p.grad.clone() for p in f.parameters() if p.grad is not None])
    assert torch.allclose(colors[0], colors[1], atol=1e-6)
    assert len(grads[0]) == len(grads[1]) > 0
    for a, b in zip(*grads, strict=True):
        assert torch.allclose(a, b, atol=1e-6)
    assert grads[1][0].abs().sum() > 0  # the hash table got its gradient through the cache


def test_a_run_counts_what_it_marched_and_trained_and_a_checkpoint_keeps_it(cube_rgb, tmp_path):
    from dronecap.nerf.compaction import MARCH_CAP
    from dronecap.nerf.resolve import resolve
    from dronecap.nerf.trainer import Trainer

    cfg = preset("test").replace(steps=40, seed=0)
    tr = Trainer(resolve(cfg, cube_rgb), cube_rgb)
    logs = tr.train(40)
    n = tr.sample_counts()
    assert 0 < n["trained"] <= n["marched"] <= 40 * MARCH_CAP * cfg.batch_samples
    assert n["trained"] == sum(log["samples"] for log in logs) <= 40 * cfg.batch_samples
    assert n["hull_fraction"] < 1.0  # the cube has alpha: the grid is carved
    tr.save(tmp_path / "ck.pt")
    assert Trainer.load(tmp_path / "ck.pt", train=cube_rgb).sample_counts() == n


def test_the_pre_pass_runs_while_it_pays_and_probes_now_and_then():
    from dronecap.nerf.compaction import MIN_DROPPED, PROBE_EVERY, due

    assert due(0, 1.0) and due(7, MIN_DROPPED)  # never measured; dropping enough
    assert not due(7, MIN_DROPPED / 2)  # a scene where nearly every sample shows
    steps = [s for s in range(64) if due(s, 0.0)]
    assert steps == list(range(0, 64, PROBE_EVERY))  # measured again now and then


def _opaque(tr) -> None:
    """Make ``tr``'s field dense everywhere (density e^3.3 ~ 26 per scene unit: the cube's rays
    are opaque after ~20 samples), so that compaction drops most of what a step marches (~70 %;
    denser still, MARCH_CAP binds before a step reaches B)."""
    with torch.no_grad():
        tr.field.encoding.table.fill_(1.0)
        for m in tr.field.density_mlp.modules():
            if isinstance(m, torch.nn.Linear):
                m.weight.fill_(0.08)


def test_a_step_trains_on_about_a_batch_while_compaction_drops_samples(cube_rgb):
    """B counts the samples trained on (the default): in a dense field compaction drops most
    marched samples, and a step marches more rays to still train on about B (never marching
    more than MARCH_CAP x B); counting the marched ones instead, a step marches at most B and
    trains on what is left."""
    from dronecap.nerf.compaction import MARCH_CAP
    from dronecap.nerf.resolve import resolve
    from dronecap.nerf.trainer import Trainer

    per_step = {}
    for counts in ("trained", "marched"):
        cfg = preset("test").replace(seed=0, batch_counts=counts)
        tr = Trainer(resolve(cfg, cube_rgb), cube_rgb)
        _opaque(tr)
        for _ in range(3):  # the first steps learn the samples per ray
            tr._march_batch()
        before = tr.sample_counts()
        _, s = tr._march_batch()
        after = tr.sample_counts()
        assert s.n == after["trained"] - before["trained"] <= cfg.batch_samples
        per_step[counts] = s.n, after["marched"] - before["marched"]
    b = cfg.batch_samples
    trained, marched = per_step["trained"]
    assert trained < 0.5 * marched  # compaction drops most samples ...
    assert trained >= 0.8 * b and marched <= MARCH_CAP * b  # ... and the step still trains ~B
    trained, marched = per_step["marched"]
    assert marched <= b and trained < 0.5 * b  # counting the marched ones: far fewer trained


def test_without_a_pre_pass_the_rays_cut_off_by_the_batch_do_not_count_as_marched(cube_rgb):
    """Compaction off: a step may march a few rays more than fit in B (the ray count comes from
    the last step's samples per ray) and cuts them off before any work; the run's counters,
    which the GAP9 model costs, must then say that every marched sample was trained on."""
    from dronecap.nerf.resolve import resolve
    from dronecap.nerf.trainer import Trainer

    cfg = preset("test").replace(steps=30, seed=0, train_min_transmittance=0.0)
    tr = Trainer(resolve(cfg, cube_rgb), cube_rgb)
    logs = tr.train(30)
    n = tr.sample_counts()
    assert n["marched"] == n["trained"] == sum(log["samples"] for log in logs) > 0


@pytest.mark.skipif(kernel("hashgrid", "auto") is None, reason="C++ hash-grid kernel unavailable")
def test_the_fused_pre_pass_keeps_the_samples_the_torch_one_keeps():
    o, d = _rays(100)  # ~10k samples: several chunks of rays, over the threads
    tn, tf, _ = ray_aabb(o, d, BOX)
    s = march(o, d, tn, tf, 0.02, None, BOX, 1000)
    for scale in (0.0, 1.0, 3.0, 30.0):  # empty, foggy, opaque, past the density clamp
        fused = _field()
        with torch.no_grad():
            fused.encoding.table.uniform_(-1, 1)
            fused.density_mlp[-1].weight.mul_(scale)
        plain = _field()
        plain.load_state_dict(fused.state_dict())
        plain.visible_samples = lambda *args: None  # the torch pre-pass
        for thresh in (1e-4, 0.5):
            a, b = visible(s, o, d, fused, thresh), visible(s, o, d, plain, thresh)
            assert torch.equal(a.ray_indices, b.ray_indices) and torch.equal(a.counts, b.counts)
            assert torch.equal(a.t_starts, b.t_starts) and torch.equal(a.t_ends, b.t_ends)
            # the C++ midpoints may round differently from torch's in the last bit
            assert torch.allclose(a.unit, b.unit, rtol=0, atol=1e-6)
            assert torch.allclose(a.encoded, b.encoded, rtol=0, atol=1e-4)
            threads = torch.get_num_threads()
            torch.set_num_threads(1)  # one thread marches every chunk of rays: the same samples
            try:
                one = visible(s, o, d, fused, thresh)
            finally:
                torch.set_num_threads(threads)
            assert torch.equal(one.ray_indices, a.ray_indices) and torch.equal(
                one.encoded, a.encoded
            )
        kept = visible(s, o, d, fused, 1e-4).n
        if scale == 0.0:
            assert kept == s.n  # density exp(0) = 1 per unit over ~2 units of ray: all kept
        if scale == 30.0:
            assert kept < s.n


@pytest.mark.skipif(kernel("hashgrid", "auto") is None, reason="C++ hash-grid kernel unavailable")
def test_the_fused_pre_pass_refuses_samples_out_of_ray_order():
    o, d = _rays(4)
    tn, tf, _ = ray_aabb(o, d, BOX)
    s = march(o, d, tn, tf, 0.05, None, BOX, 1000)
    f = _field()
    for bad in (s.ray_indices.flip(0), s.ray_indices + 4):  # decreasing; past the rays
        with pytest.raises(RuntimeError, match="non-decreasing indices of the rays"):
            f.visible_samples(o, d, (s.t_starts, s.t_ends, bad), 1e-4)
    empty = torch.zeros(0)
    none = f.visible_samples(o, d, (empty, empty, empty.long()), 1e-4)
    assert none.ray_indices.numel() == 0 and none.encoded.shape == (0, f.encoding.out_dim)
    assert none.unit.shape == (0, 3) and torch.equal(none.counts, torch.zeros(4, dtype=torch.long))


@pytest.mark.skipif(kernel("hashgrid", "auto") is None, reason="C++ hash-grid kernel unavailable")
def test_the_pre_pass_cuts_the_batch_where_whole_rays_would():
    o, d = _rays(100)
    tn, tf, _ = ray_aabb(o, d, BOX)
    s = march(o, d, tn, tf, 0.02, None, BOX, 1000)
    s = Samples(s.ray_indices, s.t_starts, s.t_ends, s.counts)
    later = s.ray_indices > 0  # and the same rays where ray 0 marched nothing
    s0 = Samples(s.ray_indices[later], s.t_starts[later], s.t_ends[later],
                 torch.cat([torch.zeros(1, dtype=torch.long), s.counts[1:]]))  # fmt: skip
    f = _field()
    with torch.no_grad():
        f.encoding.table.uniform_(-1, 1)
    rays = RayBatch(o, d, torch.zeros(100, 3), torch.zeros(100, 3), torch.zeros(100).long(),
                    torch.zeros(100))  # fmt: skip
    for samples in (s, s0):
        whole = visible(samples, o, d, f, 1e-4)
        for batch in (1, 5, whole.n // 3, whole.n - 1, whole.n, 10 * whole.n):
            want_rays, want = whole_rays(rays, whole, batch)
            cut, found = visible_in_batch(samples, o, d, f, 1e-4, batch)
            got_rays, got = whole_rays(rays, cut, batch)
            assert found == whole.n and got.n <= max(batch, int(whole.counts[0]))
            assert got_rays.origins.shape == want_rays.origins.shape
            assert torch.equal(got.counts, want.counts)
            assert torch.equal(got.ray_indices, want.ray_indices)
            assert torch.equal(got.encoded, want.encoded) and torch.equal(got.unit, want.unit)
