"""C++ ray marching against the PyTorch reference in nerf/marching.py: the very same samples."""

from __future__ import annotations

import pytest
import torch

from dronecap.nerf import march_kernel, marching
from dronecap.nerf.occupancy import GridState
from dronecap.nerf.rays import ray_aabb

AABB = torch.tensor([[-1.0, -1.2, -0.8], [1.1, 1.0, 0.9]])


@pytest.fixture(scope="module")
def cpp() -> None:
    """Build (or load from the on-disk cache) the marching kernel once per module."""
    try:
        march_kernel.load_extension()
    except Exception as err:  # no compiler on this machine
        pytest.skip(f"C++ marching kernel could not be built: {err}")


def rays(n: int, seed: int) -> tuple[torch.Tensor, torch.Tensor]:
    """[n, 3] origins and unit directions: from outside toward the box, from inside, and misses."""
    g = torch.Generator().manual_seed(seed)
    origins = torch.randn(n, 3, generator=g) * 3.0
    origins[: n // 4] = torch.rand(n // 4, 3, generator=g) - 0.5  # start inside the box
    target = torch.rand(n, 3, generator=g) * 1.6 - 0.8
    dirs = target - origins
    dirs[-(n // 8) :] = origins[-(n // 8) :]  # pointing away from the box (mostly misses)
    dirs[0] = torch.tensor([0.0, 0.0, 1.0])  # axis-aligned
    return origins, dirs / dirs.norm(dim=-1, keepdim=True)


def assert_same(a: marching.Samples, b: marching.Samples) -> None:
    """Packed samples equal bit for bit."""
    assert torch.equal(a.counts, b.counts)
    assert torch.equal(a.ray_indices, b.ray_indices)
    assert torch.equal(a.t_starts, b.t_starts) and torch.equal(a.t_ends, b.t_ends)
    assert torch.equal(a.t_resume, b.t_resume)


@pytest.mark.parametrize("occupied_fraction", [None, 0.0, 0.1, 1.0])
def test_cpp_march_equals_reference(cpp, occupied_fraction):
    origins, dirs = rays(300, seed=1)
    t_near, t_far, hit = ray_aabb(origins, dirs, AABB)
    assert 0 < int(hit.sum()) < 300  # some rays miss
    grid = None
    if occupied_fraction is not None:
        occupied = torch.rand(32**3, generator=torch.Generator().manual_seed(2)) < occupied_fraction
        grid = GridState(torch.zeros(32**3), occupied)
    step = float((AABB[1] - AABB[0]).norm()) / 256
    jitter = torch.rand(300, generator=torch.Generator().manual_seed(3))
    for offsets in (jitter, None):
        ref = marching.march(origins, dirs, t_near, t_far, step, grid, AABB, 100, offsets)
        out = march_kernel.march(origins, dirs, t_near, t_far, step, grid, AABB, 100, offsets)
        assert_same(out, ref)
        if occupied_fraction == 0.0:
            assert out.n == 0
        assert (out.counts <= 100).all()  # max_samples caps long rays
        assert (out.t_starts >= t_near[out.ray_indices]).all()
        assert (out.t_ends <= t_far[out.ray_indices]).all()


@pytest.mark.parametrize("impl", ["reference", "cpp"])
def test_march_in_rounds_of_max_kept_samples_equals_one_march(cpp, impl):
    """Marching again and again from t_resume, max_kept samples at a time (how views are
    rendered), gives the samples of one unlimited march; both implementations agree."""
    march = {"reference": marching.march, "cpp": march_kernel.march}[impl]
    origins, dirs = rays(200, seed=4)
    t_near, t_far, _ = ray_aabb(origins, dirs, AABB)
    occupied = torch.rand(16**3, generator=torch.Generator().manual_seed(5)) < 0.3
    grid = GridState(torch.zeros(16**3), occupied)
    step = float((AABB[1] - AABB[0]).norm()) / 128
    whole = march(origins, dirs, t_near, t_far, step, grid, AABB, 1000)
    assert whole.counts.max() > 3 * 5  # several rounds for some rays
    got: list[list[float]] = [[] for _ in range(200)]
    t0, alive, rounds = t_near.clone(), torch.arange(200), 0
    while alive.numel():
        s = march(
            origins[alive], dirs[alive], t0[alive], t_far[alive], step, grid, AABB, 1000, max_kept=5
        )
        if impl == "cpp":
            assert_same(
                s,
                marching.march(
                    origins[alive],
                    dirs[alive],
                    t0[alive],
                    t_far[alive],
                    step,
                    grid,
                    AABB,
                    1000,
                    max_kept=5,
                ),
            )
        assert (s.counts <= 5).all()
        for r, t in zip(alive[s.ray_indices].tolist(), s.t_starts.tolist(), strict=True):
            got[r].append(t)
        t0[alive] = s.t_resume
        alive = alive[s.t_resume < t_far[alive]]
        rounds += 1
    assert rounds > 3
    for r in range(200):
        mine = whole.t_starts[whole.ray_indices == r]
        # restarting at t_resume re-rounds t by a few ulps; the sample count is exact
        assert len(got[r]) == len(mine)
        torch.testing.assert_close(torch.tensor(got[r]), mine, atol=1e-5, rtol=0)


def test_cpp_march_no_rays_and_bad_step(cpp):
    empty = torch.zeros(0, 3)
    s = march_kernel.march(empty, empty, torch.zeros(0), torch.zeros(0), 0.1, None, AABB, 8)
    assert s.n == 0 and s.counts.shape == (0,)
    with pytest.raises(ValueError, match="positive"):
        march_kernel.march(empty, empty, torch.zeros(0), torch.zeros(0), 0.0, None, AABB, 8)
