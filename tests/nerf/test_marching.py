"""Ray marching into packed samples and the occupancy grid that prunes them."""

import math

import pytest
import torch

from dronecap.nerf import occupancy
from dronecap.nerf.backend import kernel
from dronecap.nerf.batch import RayBatch, whole_rays
from dronecap.nerf.config import preset
from dronecap.nerf.draws import grid_draws
from dronecap.nerf.field import Field
from dronecap.nerf.marching import march
from dronecap.nerf.rays import ray_aabb

BOX = torch.tensor([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]])


def _rays():
    o = torch.tensor([[0.0, 0.0, -3.0], [0.0, 5.0, -3.0], [0.2, 0.1, 0.0], [1.0, 0.3, 0.3]])
    d = torch.tensor([[0.0, 0.0, 1.0], [0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [-1.0, 0.0, 0.0]])
    return o, d


def test_counts_positions_and_bounds_without_grid():
    o, d = _rays()
    tn, tf, _ = ray_aabb(o, d, BOX)
    s = march(o, d, tn, tf, 0.25, None, BOX, 1000)
    # ray 0 crosses 2 units: 8 steps; ray 1 misses; ray 2 starts inside, 0.8 from the face:
    # ceil(0.8 / 0.25) = 4 candidates with midpoints 0.125 .. 0.875, the last past t_far,
    # dropped -> 3; ray 3 starts exactly on the +x face going in: 8
    assert s.counts.tolist() == [8, 0, 3, 8]
    assert torch.all(s.ray_indices[1:] >= s.ray_indices[:-1])
    mids = 0.5 * (s.t_starts + s.t_ends)
    pts = o[s.ray_indices] + d[s.ray_indices] * mids[:, None]
    assert torch.all(pts >= -1) and torch.all(pts <= 1)  # only points inside the AABB
    assert torch.all(s.t_starts >= tn[s.ray_indices]) and torch.all(s.t_ends <= tf[s.ray_indices])
    assert torch.allclose(s.t_starts[:2], torch.tensor([2.0, 2.25]))  # box entry at t = 2


def test_max_samples_and_zero_step():
    o, d = _rays()
    tn, tf, _ = ray_aabb(o, d, BOX)
    s = march(o, d, tn, tf, 0.01, None, BOX, 16)
    assert int(s.counts.max()) == 16
    with pytest.raises(ValueError, match="positive"):
        march(o, d, tn, tf, 0.0, None, BOX, 16)


def test_grid_prunes_empty_cells():
    cfg = occupancy.GridConfig(res=4)
    st = occupancy.init_state(cfg)
    st.occupied[:] = False
    # occupy only the cell containing (0.1, 0.1, 0.6): indices (2, 2, 3)
    st.occupied[(2 * 4 + 2) * 4 + 3] = True
    o = torch.tensor([[0.1, 0.1, -3.0]])
    d = torch.tensor([[0.0, 0.0, 1.0]])
    tn, tf, _ = ray_aabb(o, d, BOX)
    s = march(o, d, tn, tf, 0.1, st, BOX, 100)
    z = (o[0, 2] + 0.5 * (s.t_starts + s.t_ends)).tolist()
    assert len(z) == 5 and all(0.5 <= v <= 1.0 for v in z)


def test_whole_rays_cuts_the_batch_at_a_ray_boundary():
    o, d = _rays()
    tn, tf, _ = ray_aabb(o, d, BOX)
    s = march(o, d, tn, tf, 0.25, None, BOX, 1000)
    s.encoded = torch.arange(s.n, dtype=torch.float32)[:, None].expand(-1, 2).contiguous()
    rays = RayBatch(o, d, torch.zeros(len(o), 3), torch.zeros(len(o), 3), torch.zeros(len(o)),
                    torch.zeros(len(o)))  # fmt: skip
    for budget, want in ((11, [8, 0, 3]), (10, [8, 0]), (1, [8])):  # at least one whole ray
        r, t = whole_rays(rays, s, budget)
        assert t.counts.tolist() == want and r.origins.shape[0] == len(want)
        assert t.n == sum(want) and t.ray_indices.tolist() == sorted(t.ray_indices.tolist())
        assert torch.equal(t.encoded[:, 0], torch.arange(t.n, dtype=torch.float32))
    r, t = whole_rays(rays, s, s.n)  # everything fits: the batch as it was
    assert t is s and r is rays


def test_grid_schedule_matches_instant_ngp():
    cfg = occupancy.GridConfig(res=8, every=16)
    due = [s for s in range(600) if occupancy.due(cfg, s)]
    assert due[:33] == list(range(33))[:32] + [32]  # every step until 32
    assert 34 in due and 35 not in due  # then every 2 steps (step // 16 = 2)
    assert [s for s in due if s >= 512][:3] == [512, 528, 544]  # then every 16


def test_grid_schedule_ramp_sets_how_fast_the_interval_grows():
    cfg = occupancy.GridConfig(res=8, every=16, ramp=4)
    due = [s for s in range(200) if occupancy.due(cfg, s)]
    assert due[:9] == list(range(9))  # every step until step 8 (step // 4 == 2)
    assert 9 not in due and 10 in due
    assert [s for s in due if s >= 64][:3] == [64, 80, 96]  # every 16 from step 64 on


def test_grid_update_thresholds_density():
    cfg = occupancy.GridConfig(res=4, warmup=10)
    st = occupancy.init_state(cfg)
    g = torch.Generator().manual_seed(0)

    def density(p):  # dense in the x > 0 half only
        return torch.where(p[:, 0] > 0, 100.0, 0.0)

    st = occupancy.update(cfg, st, 0, density, BOX, 0.01, g)
    occ = st.occupied.reshape(4, 4, 4)
    assert occ[2:].all() and not occ[:2].any()
    assert math.isclose(float(st.density.max()), 1.0, rel_tol=1e-6)  # 100 * 0.01
    # after warm-up with zero density, the EMA decays
    st2 = occupancy.update(cfg, st, 20, lambda p: torch.zeros(len(p)), BOX, 0.01, g)
    assert math.isclose(float(st2.density.max()), 0.95, rel_tol=1e-6)


def test_grid_update_after_warm_up_samples_quarters_of_the_allowed_cells():
    cfg = occupancy.GridConfig(res=8, warmup=0)
    allowed = torch.zeros(512, dtype=torch.bool)
    allowed[:64] = True  # the visual hull: 64 of 512 cells
    st = occupancy.restrict(occupancy.init_state(cfg), allowed)
    seen = []

    def density(p):
        seen.append(occupancy.cell_index(p, BOX, 8))
        return torch.ones(len(p))

    occupancy.update(cfg, st, 300, density, BOX, 0.01, torch.Generator().manual_seed(0))
    cells = torch.cat(seen)
    assert cells.numel() == 2 * (64 // 4)  # a quarter uniform + a quarter occupied, of 64
    assert bool(allowed[cells].all())  # never outside the hull


@pytest.mark.skipif(kernel("hashgrid", "auto") is None, reason="C++ hash-grid kernel unavailable")
@pytest.mark.parametrize("hull", [False, True])
@pytest.mark.parametrize("step", [0, 300])  # warm-up (every cell), then quarters
def test_the_fused_grid_update_gives_the_torch_ones_grid(hull, step):
    torch.manual_seed(0)
    field = Field(preset("test").replace(n_max=64, mlp_dtype="fp32"), 3, BOX.numpy())
    with torch.no_grad():
        field.encoding.table.uniform_(-1, 1)
        field.density_mlp[-1].weight.mul_(20.0)  # densities from ~0 to the clamp
    cfg = occupancy.GridConfig(res=16, warmup=100)
    state = occupancy.init_state(cfg)
    state.density.uniform_(0.0, 0.05)  # an EMA to decay
    if hull:
        state = occupancy.restrict(state, torch.rand(16**3) < 0.6)
    out = []
    for refresh in (field.grid_refresh, None):
        g = torch.Generator().manual_seed(1)
        out.append(occupancy.update(cfg, state, step, field.density, BOX, 0.05, g, refresh))
    fused, plain = out
    assert torch.allclose(fused.density, plain.density, rtol=1e-5, atol=1e-8)
    assert torch.equal(fused.occupied, plain.occupied)
    assert fused.occupied.any() and not fused.occupied.all()
    assert (fused.allowed is None) == (not hull) and (fused.pool is None) == (not hull)


def _draws():
    ext = kernel("march", "auto")
    if ext is None:
        pytest.skip("C++ marching kernel unavailable")
    return ext.grid_draws


def test_the_kernels_grid_draws_follow_the_update_rules():
    draws = _draws()
    occupied = torch.zeros(16**3, dtype=torch.bool)
    occupied[torch.tensor([5, 77, 300, 4000])] = True
    pool = torch.arange(0, 16**3, 3)
    cells, jitter = draws(occupied, pool, 0, True, 1)  # warm-up: every allowed cell
    assert torch.equal(cells, pool) and jitter.shape == (pool.numel(), 3)
    cells, jitter = draws(occupied, pool, 5000, False, 2)  # a quarter from each
    assert cells.shape == (10000,) and jitter.shape == (10000, 3)
    assert torch.isin(cells[:5000], pool).all()
    assert torch.isin(cells[5000:], occupied.nonzero().squeeze(1)).all()
    assert len(cells[5000:].unique()) == 4  # each occupied cell drawn
    assert cells[:5000].unique().numel() > 0.6 * pool.numel()  # spread over the pool
    assert 0.0 <= float(jitter.min()) and float(jitter.max()) < 1.0
    assert abs(float(jitter.mean()) - 0.5) < 0.01 and abs(float(jitter.std()) - 12**-0.5) < 0.01
    cells, _ = draws(torch.zeros(16**3, dtype=torch.bool), torch.zeros(0, dtype=torch.int64),
                     100, False, 3)  # fmt: skip
    assert cells.shape == (100,) and int(cells.max()) < 16**3  # none occupied: uniform only


@pytest.mark.parametrize("warm", [True, False])
@pytest.mark.parametrize("hull", [False, True])
def test_torch_ops_draw_the_kernels_grid_cells_and_points(warm, hull):
    draws = _draws()
    occupied = torch.rand(32**3, generator=torch.Generator().manual_seed(1)) < 0.1
    pool = torch.arange(0, 32**3, 5) if hull else None
    empty = torch.zeros(0, dtype=torch.int64)
    for occ in (occupied, torch.zeros_like(occupied)):  # and none occupied
        got = draws(occ, empty if pool is None else pool, 1500, warm, 2**61 + 12345)
        want = grid_draws(occ, pool, 1500, warm, 2**61 + 12345)
        assert all(torch.equal(a, b) for a, b in zip(got, want, strict=True))


def test_the_kernels_grid_draws_do_not_depend_on_the_threads():
    draws, threads = _draws(), torch.get_num_threads()
    occupied = torch.rand(64**3, generator=torch.Generator().manual_seed(0)) < 0.3
    empty = torch.zeros(0, dtype=torch.int64)
    try:
        torch.set_num_threads(1)
        one = draws(occupied, empty, 40000, False, 7)
        torch.set_num_threads(2)
        two = draws(occupied, empty, 40000, False, 7)
    finally:
        torch.set_num_threads(threads)
    assert all(torch.equal(a, b) for a, b in zip(one, two, strict=True))
    other = draws(occupied, empty, 40000, False, 8)
    assert not torch.equal(one[1], other[1])  # another seed, other points


def test_the_fused_grid_update_gives_the_torch_ones_grid_with_the_kernels_draws():
    field = Field(preset("test").replace(n_max=64, mlp_dtype="fp32"), 3, BOX.numpy())
    with torch.no_grad():
        field.encoding.table.uniform_(-1, 1)
    ext = kernel("march", "auto")
    if ext is None or kernel("hashgrid", "auto") is None:
        pytest.skip("C++ kernels unavailable")
    cfg = occupancy.GridConfig(res=16, warmup=100)
    state = occupancy.init_state(cfg)
    out = []
    for refresh in (field.grid_refresh, None):
        g = torch.Generator().manual_seed(1)
        out.append(occupancy.update(cfg, state, 300, field.density, BOX, 0.05, g, refresh, ext))
    assert torch.allclose(out[0].density, out[1].density, rtol=1e-5, atol=1e-8)
    assert torch.equal(out[0].occupied, out[1].occupied)
