"""Speed of the hash encoding backends, a training-step proxy, and ray marching on this CPU.

For 8192 points at the tiny-dronerf encoding (L=16, F=2, T=2^13, n_min=16, n_max=2048) it
measures forward+backward of the encoding alone, also as 8 tiles of 1024 points (the trainer's
accumulation), and a full step proxy (encoding, density MLP 32->64->16, colour MLP
31->64->64->3, MSE, backward, Adam) for each backend; then the occupancy-grid ray marching
(reference vs C++) of one training batch. Medians of repeats after warm-up; prints a table and
writes benchmarks/results/hashgrid_speed.md.

    .venv/bin/python benchmarks/hashgrid_speed.py [--repeats 20] [--threads 1 2] [--skip-compile]
"""

from __future__ import annotations

import argparse
import os
import statistics
import time
from collections.abc import Callable
from pathlib import Path

import torch

from dronecap.nerf import march_kernel, marching
from dronecap.nerf.hashgrid import HashGrid, hash_encode_cpp
from dronecap.nerf.occupancy import GridState
from dronecap.nerf.rays import ray_aabb

REPO = Path(__file__).resolve().parents[1]
N = 8192
TILE = 1024
CONFIG = dict(levels=16, features=2, log2_hashmap=13, n_min=16, n_max=2048)


class Timing(float):
    """A median wall time in ms that also carries the fastest repeat (``best``)."""

    best: float

    def __str__(self) -> str:
        return f"{float(self):.2f} ({self.best:.2f})"


def median_ms(fn: Callable[[], object], repeats: int, warmup: int = 5) -> Timing:
    """Median (and best) wall time of ``fn()`` in ms over ``repeats`` calls after ``warmup``."""
    for _ in range(warmup):
        fn()
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    timing = Timing(1e3 * statistics.median(times))
    timing.best = 1e3 * min(times)
    return timing


def mlp(sizes: list[int]) -> torch.nn.Sequential:
    """Bias-free ReLU MLP with the given layer widths (Instant-NGP's fully fused MLP shape)."""
    layers: list[torch.nn.Module] = []
    for i, (a, b) in enumerate(zip(sizes[:-1], sizes[1:], strict=True)):
        layers.append(torch.nn.Linear(a, b, bias=False))
        if i < len(sizes) - 2:
            layers.append(torch.nn.ReLU())
    return torch.nn.Sequential(*layers)


def encoding_ms(grid: HashGrid, x: torch.Tensor, repeats: int, tile: int, mode: str = "") -> Timing:
    """Forward + backward of the encoding of ``x`` in tiles of ``tile`` points (ms)."""
    grad_out = torch.randn(x.shape[0], grid.out_dim)

    def run() -> None:
        grid.table.grad = None
        for s in range(0, x.shape[0], tile):
            xs = x[s : s + tile]
            if mode:
                out = hash_encode_cpp(
                    xs, grid.table, grid.resolutions, grid.offsets, grid.log2_hashmap, mode
                )
            else:
                out = grid(xs)
            out.backward(grad_out[s : s + tile])

    return median_ms(run, repeats)


def step_proxy_ms(grid: HashGrid, x: torch.Tensor, repeats: int, fused_adam: bool) -> Timing:
    """Encoding + both MLPs + MSE + backward + Adam on all of ``x`` at once (ms)."""
    torch.manual_seed(0)
    density, colour = mlp([32, 64, 16]), mlp([31, 64, 64, 3])
    sh = torch.randn(x.shape[0], 16)
    target = torch.rand(x.shape[0], 3)
    params = [grid.table, *density.parameters(), *colour.parameters()]
    opt = torch.optim.Adam(
        params, lr=1e-2, betas=(0.9, 0.99), eps=1e-15, fused=fused_adam, foreach=not fused_adam
    )

    def step() -> None:
        opt.zero_grad(set_to_none=True)
        h = density(grid(x))
        rgb = colour(torch.cat([h[:, 1:], sh], dim=-1))
        loss = torch.nn.functional.mse_loss(torch.sigmoid(rgb), target)
        loss.backward()
        opt.step()

    return median_ms(step, repeats)


def march_rows(repeats: int) -> list[tuple[str, Timing]]:
    """Reference vs C++ marching of 1000 rays through a 128^3 grid with a ball occupied (ms)."""
    g = torch.Generator().manual_seed(0)
    aabb = torch.tensor([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]])
    origins = torch.nn.functional.normalize(torch.randn(1000, 3, generator=g), dim=-1) * 4.0
    dirs = torch.nn.functional.normalize(
        torch.rand(1000, 3, generator=g) - 0.5 - origins / 4.0, dim=-1
    )
    t_near, t_far, _ = ray_aabb(origins, dirs, aabb)
    centres = (torch.stack(torch.meshgrid(*[torch.arange(128)] * 3, indexing="ij"), -1) + 0.5) / 64
    occupied = ((centres - 1.0).norm(dim=-1) < 0.5).reshape(-1)  # a ball of radius 0.5
    grid = GridState(torch.zeros(128**3), occupied)
    step = 2.0 * 3**0.5 / 1024
    jitter = torch.rand(1000, generator=g)
    args = (origins, dirs, t_near, t_far, step, grid, aabb, 1024, jitter)
    n = marching.march(*args).n
    ref = median_ms(lambda: marching.march(*args), max(repeats // 2, 5), warmup=2)
    cpp = median_ms(lambda: march_kernel.march(*args), repeats)
    label = (
        f"march 1000 rays -> {n} samples (128^3 grid, {float(occupied.float().mean()):.1%} occ.)"
    )
    return [(f"{label}, reference", ref), (f"{label}, C++", cpp)]


def measure(args: argparse.Namespace) -> list[tuple[str, Timing]]:
    """Every measurement of this benchmark at the current thread count: (name, ms) rows."""
    torch.manual_seed(0)
    x = torch.rand(N, 3)
    rows: list[tuple[str, Timing]] = []

    def add(name: str, ms: Timing) -> None:
        rows.append((name, ms))
        print(f"{torch.get_num_threads()} thr  {name:70s} {ms} ms", flush=True)

    def encoding(grid: HashGrid, tile: int, what: str, mode: str = "") -> None:
        points = f"{N} points" if tile == N else f"8 tiles of {TILE}"
        add(f"encoding fwd+bwd, {points}, {what}", encoding_ms(grid, x, args.repeats, tile, mode))

    def step_proxy(grid: HashGrid, what: str, fused_adam: bool) -> None:
        add(f"step proxy, {what}", step_proxy_ms(grid, x, args.repeats, fused_adam=fused_adam))

    backends = ["torch", "cpp"] + ([] if args.skip_compile else ["compile"])
    for backend in backends:
        grid = HashGrid(**CONFIG, backend=backend)
        encoding(grid, N, backend)
        encoding(grid, TILE, backend)
        step_proxy(grid, f"{backend}, fused Adam", fused_adam=True)
        if backend == "cpp":
            inplace = HashGrid(**CONFIG, backend=backend, inplace_grad=True)
            encoding(inplace, TILE, "cpp inplace_grad")
            step_proxy(grid, f"{backend}, foreach Adam (torch default)", fused_adam=False)
            for mode in ("level", "atomic", "partial"):
                encoding(grid, N, f"cpp backward_mode={mode}", mode)
    for dtype in (torch.float16, torch.bfloat16):
        encoding(HashGrid(**CONFIG, backend="cpp", dtype=dtype), N, f"cpp, {dtype} storage")
    grid = HashGrid(**CONFIG, backend="cpp")
    big = torch.rand(1 << 16, 3)
    with torch.no_grad():
        add("encoding forward only (no_grad), 65536 points, cpp", median_ms(lambda: grid(big), 10))
    for name, ms in march_rows(args.repeats):
        add(name, ms)
    return rows


def main() -> None:
    """Run the measurements at each thread count, print the table and write the results file."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=20)
    parser.add_argument("--threads", type=int, nargs="+", default=[1, torch.get_num_threads()])
    parser.add_argument("--skip-compile", action="store_true", help="leave out torch.compile")
    args = parser.parse_args()
    columns = {}
    loads = []
    for threads in args.threads:
        torch.set_num_threads(threads)
        columns[threads] = dict(measure(args))
        loads.append(os.getloadavg()[0])
    names = list(next(iter(columns.values())))
    head = "| measurement | " + " | ".join(f"{t} thread(s), ms" for t in columns) + " |\n"
    table = head + "|---|" + "---:|" * len(columns) + "\n"
    for name in names:
        table += f"| {name} | " + " | ".join(str(c[name]) for c in columns.values()) + " |\n"
    threads = " ".join(str(t) for t in args.threads)
    text = (
        "# Hash encoding and marching speed\n\n"
        f"Encoding L=16 F=2 T=2^13 n_min=16 n_max=2048; torch {torch.__version__}; medians of "
        f"{args.repeats} repeats after warm-up, the fastest repeat in brackets. The machine "
        "(2 cores) was shared with other jobs: "
        f"load average {', '.join(f'{v:.1f}' for v in loads)} after each column, so absolute "
        "times are inflated (most for 2 threads, whose OpenMP regions stall when a core is "
        "taken); compare rows within a column.\n"
        "Step proxy = encoding + density MLP 32->64->16 + colour MLP 31->64->64->3 (bias-free, "
        f"ReLU) + MSE + backward + Adam on {N} points.\n\n"
        f"Command: `.venv/bin/python benchmarks/hashgrid_speed.py --repeats {args.repeats} "
        f"--threads {threads}{' --skip-compile' if args.skip_compile else ''}`\n\n" + table
    )
    print(table)
    out = REPO / "benchmarks" / "results" / "hashgrid_speed.md"
    out.write_text(text)
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
