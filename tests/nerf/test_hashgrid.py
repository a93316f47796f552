"""Hash encoding: hand-worked indexing, C++ kernel against the reference, low-precision storage."""

from __future__ import annotations

import pytest
import torch

from dronecap.nerf.hashgrid import (
    HashGrid,
    hash_encode_cpp,
    hash_encode_reference,
    level_offsets,
    level_resolutions,
    load_extension,
)


@pytest.fixture(scope="module")
def cpp() -> None:
    """Build (or load from the on-disk cache) the C++ kernel once per test module."""
    try:
        load_extension()
    except Exception as err:  # no compiler on this machine
        pytest.skip(f"C++ hash grid kernel could not be built: {err}")


def edge_points(n: int, seed: int = 0) -> torch.Tensor:
    """[n + 9, 3] random points plus points on the 0 and 1 faces, outside the cube, and NaN."""
    g = torch.Generator().manual_seed(seed)
    special = torch.tensor(
        [
            [0.0, 0.0, 0.0],
            [1.0, 1.0, 1.0],
            [1.0, 0.0, 1.0],
            [0.0, 0.5, 1.0],
            [-0.5, 2.0, 0.5],
            [1.0 + 1e-7, -1e-7, 0.25],
            [float("nan"), 0.5, float("inf")],
            [float("-inf"), 1.0, 0.0],
            [0.999999, 1e-7, 0.5],
        ]
    )
    return torch.cat([torch.rand(n, 3, generator=g) * 1.2 - 0.1, special])


def test_levels_follow_instant_ngp_geometric_series():
    res = level_resolutions(16, 16, 2048)
    # b = 128 ** (1/15) = 1.3819...; floor(16 b) = 22, floor(16 b^2) = 30, last level exactly 2048.
    assert res[:3] == [16, 22, 30] and res[-1] == 2048 and len(res) == 16
    offsets = level_offsets(res, 13)
    # 17^3 = 4913 <= 8192 rows: level 0 is dense; 23^3 = 12167 > 8192: hashed from level 1.
    assert offsets[:3] == [0, 4913, 4913 + 8192] and offsets[-1] == 4913 + 15 * 8192
    assert level_resolutions(1, 8, 8) == [8]


def test_hand_worked_dense_and_hashed_rows():
    # Levels res 2 (dense: 3^3 = 27 <= 64 rows) and res 4 (hashed: 5^3 = 125 > 64 = T).
    res, log2_t = [2, 4], 6
    offsets = level_offsets(res, log2_t)
    assert offsets == [0, 27, 27 + 64]
    table = torch.arange(offsets[-1], dtype=torch.float32)[:, None]  # row r holds value r
    # x = (0.5, 1, 0): level 0 p = (1, 2, 0) -> corner (1, 2, 0), dense row 1 + 2*3 + 0*9 = 7.
    # Level 1 p = (2, 4, 0) -> corner (2, 4, 0): 2 ^ (4 * 2654435761) ^ 0 mod 64;
    # 2654435761 mod 64 = 49, 4 * 49 mod 64 = 4, 2 ^ 4 = 6 -> row 27 + 6 = 33.
    # x = (0.25, 0, 0): level 0 p = (0.5, 0, 0), halfway between rows 0 and 1 -> 0.5;
    # level 1 p = (1, 0, 0) -> corner (1, 0, 0): hash 1 -> row 28.
    x = torch.tensor([[0.5, 1.0, 0.0], [0.25, 0.0, 0.0]])
    expected = torch.tensor([[7.0, 33.0], [0.5, 28.0]])
    torch.testing.assert_close(hash_encode_reference(x, table, res, offsets, log2_t), expected)


def test_hand_worked_rows_cpp(cpp):
    res, log2_t = [2, 4], 6
    offsets = level_offsets(res, log2_t)
    table = torch.arange(offsets[-1], dtype=torch.float32)[:, None]
    x = torch.tensor([[0.5, 1.0, 0.0], [0.25, 0.0, 0.0]])
    out = hash_encode_cpp(x, table, res, offsets, log2_t)
    torch.testing.assert_close(out, torch.tensor([[7.0, 33.0], [0.5, 28.0]]))


@pytest.mark.parametrize("mode", ["level", "atomic", "partial"])
@pytest.mark.parametrize("features", [2, 3])
def test_cpp_matches_reference_forward_and_backward(cpp, mode, features):
    res = level_resolutions(6, 4, 300)  # dense and hashed levels
    offsets = level_offsets(res, 10)
    table = torch.randn(offsets[-1], features, requires_grad=True)
    x = edge_points(3000)
    grad_out = torch.randn(x.shape[0], 6 * features)
    ref = hash_encode_reference(x, table, res, offsets, 10)
    (grad_ref,) = torch.autograd.grad(ref, table, grad_out)
    out = hash_encode_cpp(x, table, res, offsets, 10, backward_mode=mode)
    (grad,) = torch.autograd.grad(out, table, grad_out)
    torch.testing.assert_close(out, ref, rtol=1e-5, atol=1e-5)
    torch.testing.assert_close(grad, grad_ref, rtol=1e-4, atol=1e-4)
    assert out.isfinite().all() and grad.isfinite().all()


@pytest.mark.filterwarnings("ignore:Input #0 requires gradient and is not a double")
@pytest.mark.parametrize("backend", ["torch", "cpp"])
def test_gradient_check_tiny(cpp, backend):
    grid = HashGrid(levels=2, features=2, log2_hashmap=5, n_min=2, n_max=5, backend=backend)
    x = edge_points(5, seed=1)
    table = torch.randn_like(grid.table, dtype=torch.float32).requires_grad_()

    def encode(t: torch.Tensor) -> torch.Tensor:
        fn = hash_encode_cpp if backend == "cpp" else hash_encode_reference
        return fn(x, t, grid.resolutions, grid.offsets, grid.log2_hashmap)

    # The encoding is linear in the table, so float32 finite differences are accurate.
    assert torch.autograd.gradcheck(
        encode, (table,), eps=1e-2, atol=1e-3, rtol=1e-3, fast_mode=True
    )


@pytest.mark.parametrize("backend", ["torch", "cpp"])
def test_largest_level_hash_has_no_overflow(cpp, backend):
    res, log2_t = 2**15, 22
    offsets = level_offsets([res], log2_t)
    rows = torch.arange(offsets[-1], dtype=torch.float32)
    table = torch.stack([rows, -rows], dim=1)  # F = 2: the C++ kernel's vectorised path
    coords = [(32768, 32768, 32768), (32767, 1, 32768), (12345, 32000, 29999), (0, 32768, 7)] * 5
    # x = c / 2^15 is exact in float32 and lands exactly on corner c (weight 1).
    x = torch.tensor(coords, dtype=torch.float32) / res
    fn = hash_encode_cpp if backend == "cpp" else hash_encode_reference
    out = fn(x, table, [res], offsets, log2_t)
    expected = [((a * 1) ^ (b * 2654435761) ^ (c * 805459861)) % 2**log2_t for a, b, c in coords]
    assert out[:, 0].long().tolist() == expected
    assert (-out[:, 1]).long().tolist() == expected


@pytest.mark.parametrize("dtype", [torch.float16, torch.bfloat16])
def test_low_precision_storage_is_finite_and_close(cpp, dtype):
    torch.manual_seed(0)
    full = HashGrid(8, 2, 10, 4, 256, backend="cpp")
    low = HashGrid(8, 2, 10, 4, 256, backend="cpp", dtype=dtype)
    with torch.no_grad():
        full.table.normal_(0.0, 0.5)
        low.table.copy_(full.table)
        low.table[:5] = 1e6  # beyond float16's range: stored saturated (65504), not inf
        full.table[:5] = min(1e6, torch.finfo(dtype).max)
    x = edge_points(500)
    out, out_low = full(x), low(x)
    assert out_low.isfinite().all()
    # Relative rounding of one stored value: 2^-11 (float16), 2^-8 (bfloat16).
    ulp = 2.0**-11 if dtype == torch.float16 else 2.0**-8
    torch.testing.assert_close(out_low, out, rtol=ulp, atol=ulp)
    out_low.square().sum().backward()
    assert low.table.grad is not None and low.table.grad.isfinite().all()
    low.round_storage_()
    assert torch.equal(low.table, low.table.to(dtype).float())


def test_backends_agree_and_bad_backend_raises(cpp):
    x = edge_points(200)
    grids = [HashGrid(4, 2, 8, 4, 64, backend=b) for b in ("torch", "cpp", "auto")]
    for g in grids[1:]:
        g.load_state_dict(grids[0].state_dict())
    outs = [g(x) for g in grids]
    assert outs[0].shape == (x.shape[0], grids[0].out_dim) == (209, 8)
    torch.testing.assert_close(outs[1], outs[0])
    torch.testing.assert_close(outs[2], outs[0])
    from dronecap.errors import InputError

    with pytest.raises(InputError, match="unknown backend"):
        HashGrid(4, 2, 8, 4, 64, backend="cuda")


@pytest.mark.parametrize("dtype", [torch.float32, torch.float16])
def test_inplace_grad_accumulates_like_autograd(cpp, dtype):
    plain = HashGrid(6, 2, 10, 4, 300, backend="cpp", dtype=dtype)
    fused = HashGrid(6, 2, 10, 4, 300, backend="cpp", dtype=dtype, inplace_grad=True)
    fused.load_state_dict(plain.state_dict())
    x = edge_points(2000)
    grad_out = torch.randn(x.shape[0], 12)
    for grid in (plain, fused):  # two tiles accumulate into .grad, starting from None
        for tile in (slice(0, 1000), slice(1000, None)):
            grid(x[tile]).backward(grad_out[tile])
    assert fused.table.grad is not None and fused.table.grad.abs().sum() > 0
    torch.testing.assert_close(fused.table.grad, plain.table.grad, rtol=1e-5, atol=1e-6)


def test_auto_falls_back_to_reference_when_the_kernel_cannot_build(monkeypatch, capsys):
    from dronecap.errors import InputError
    from dronecap.nerf import backend

    def no_compiler(name):
        raise RuntimeError("no C++ compiler in this test")

    monkeypatch.setattr(backend, "load", no_compiler)
    monkeypatch.setattr(backend, "_said", set())
    x = edge_points(50)
    grid = HashGrid(4, 2, 8, 4, 64, backend="auto")
    out = grid(x)
    expected = hash_encode_reference(x, grid.table, grid.resolutions, grid.offsets, 8)
    torch.testing.assert_close(out, expected)
    HashGrid(4, 2, 8, 4, 64, backend="auto")(x)  # the notice comes once per process
    err = capsys.readouterr().err
    assert err.count("using the PyTorch reference kernels, ~8x slower") == 1
    assert "no C++ compiler in this test" in err
    with pytest.raises(InputError, match="cannot be built: no C\\+\\+ compiler"):
        HashGrid(4, 2, 8, 4, 64, backend="cpp")(x)


def test_kernel_cache_key_follows_torch_python_and_source(monkeypatch, tmp_path):
    """The build folder changes with the torch version, the Python version, the checkout and
    the C++ source, so two installs on one machine never share (and rebuild) each other's
    kernel."""
    import sys

    from dronecap.nerf import backend

    base = backend.cache_key("hashgrid")
    assert base == backend.cache_key("hashgrid")  # deterministic
    assert base != backend.cache_key("march")  # another source
    monkeypatch.setattr(torch, "__version__", "0.0.0-other")
    other_torch = backend.cache_key("hashgrid")
    monkeypatch.undo()
    monkeypatch.setattr(sys, "version", "2.7.18 (other)")
    other_python = backend.cache_key("hashgrid")
    monkeypatch.undo()
    copy = tmp_path / "checkout"  # the same source in another checkout: its own build
    copy.mkdir()
    (copy / "hashgrid.cpp").write_bytes((backend.CSRC / "hashgrid.cpp").read_bytes())
    monkeypatch.setattr(backend, "CSRC", copy)
    other_checkout = backend.cache_key("hashgrid")
    (copy / "hashgrid.cpp").write_bytes((copy / "hashgrid.cpp").read_bytes() + b"// edited\n")
    other_source = backend.cache_key("hashgrid")
    keys = {base, other_torch, other_python, other_checkout, other_source}
    assert len(keys) == 5
    assert backend.build_dir("hashgrid").name == f"hashgrid-{other_source}"


def test_stale_torch_build_lock_does_not_hang() -> None:
    """A build killed mid-way leaves torch's `lock` file; the next load must not wait forever."""
    import subprocess
    import sys

    from dronecap.nerf.backend import build_dir

    load_extension()  # built (or loaded from the cache) in this process
    lock = build_dir("hashgrid") / "lock"
    lock.touch()
    code = "from dronecap.nerf.hashgrid import load_extension; load_extension()"
    done = subprocess.run([sys.executable, "-c", code], timeout=300, capture_output=True)
    assert done.returncode == 0, done.stderr.decode()[-500:]
    assert not lock.exists()
