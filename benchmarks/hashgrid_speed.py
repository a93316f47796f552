"""Speed of the hash encoding backends and of a training-step proxy on this CPU.

Measures, for 8192 points at the tiny-dronerf encoding (L=16, F=2, T=2^13, n_min=16,
n_max=2048): forward+backward of the encoding alone, and a full step proxy (encoding, density
MLP 32->64->16, colour MLP 31->64->64->3, MSE loss, backward, Adam), for each backend. Prints a
table of medians over repeats after warm-up and writes it to benchmarks/results/hashgrid_speed.md.

    .venv/bin/python benchmarks/hashgrid_speed.py [--repeats 20] [--skip-compile]
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from collections.abc import Callable
from pathlib import Path

import torch

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from dronecap.nerf.hashgrid import HashGrid, hash_encode_cpp  # noqa: E402

N = 8192
CONFIG = dict(levels=16, features=2, log2_hashmap=13, n_min=16, n_max=2048)


def median_ms(fn: Callable[[], None], repeats: int, warmup: int = 5) -> float:
    """Median wall time of ``fn()`` in milliseconds over ``repeats`` calls after ``warmup``."""
    for _ in range(warmup):
        fn()
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return 1e3 * statistics.median(times)


def mlp(sizes: list[int]) -> torch.nn.Sequential:
    """Bias-free ReLU MLP with the given layer widths (Instant-NGP's fully fused MLP shape)."""
    layers: list[torch.nn.Module] = []
    for i, (a, b) in enumerate(zip(sizes[:-1], sizes[1:], strict=True)):
        layers.append(torch.nn.Linear(a, b, bias=False))
        if i < len(sizes) - 2:
            layers.append(torch.nn.ReLU())
    return torch.nn.Sequential(*layers)


def encoding_only(grid: HashGrid, x: torch.Tensor, repeats: int, **kw) -> float:
    """Forward + backward of the encoding alone (ms)."""
    grad_out = torch.randn(N, grid.out_dim)

    def step() -> None:
        grid.table.grad = None
        if kw:
            out = hash_encode_cpp(x, grid.table, grid.resolutions, grid.offsets, 13, **kw)
        else:
            out = grid(x)
        out.backward(grad_out)

    return median_ms(step, repeats)


def step_proxy(grid: HashGrid, x: torch.Tensor, repeats: int) -> float:
    """Encoding + both MLPs + MSE + backward + Adam (ms)."""
    torch.manual_seed(0)
    density, colour = mlp([32, 64, 16]), mlp([31, 64, 64, 3])
    sh = torch.randn(N, 16)
    target = torch.rand(N, 3)
    params = [grid.table, *density.parameters(), *colour.parameters()]
    opt = torch.optim.Adam(params, lr=1e-2, betas=(0.9, 0.99), eps=1e-15, fused=True)

    def step() -> None:
        opt.zero_grad(set_to_none=True)
        h = density(grid(x))
        rgb = colour(torch.cat([h[:, 1:], sh], dim=-1))
        loss = torch.nn.functional.mse_loss(torch.sigmoid(rgb), target)
        loss.backward()
        opt.step()

    return median_ms(step, repeats)


def main() -> None:
    """Run the measurements, print the table and write the results file."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=20)
    parser.add_argument("--skip-compile", action="store_true", help="leave out torch.compile")
    args = parser.parse_args()
    torch.manual_seed(0)
    x = torch.rand(N, 3)
    rows = []
    backends = ["torch", "cpp"] + ([] if args.skip_compile else ["compile"])
    for backend in backends:
        grid = HashGrid(**CONFIG, backend=backend)
        enc = encoding_only(grid, x, args.repeats)
        full = step_proxy(grid, x, args.repeats)
        rows.append((f"{backend}", f"{enc:.2f}", f"{full:.2f}"))
        print(rows[-1], flush=True)
    grid = HashGrid(**CONFIG, backend="cpp")
    for mode in ("level", "atomic", "partial"):
        enc = encoding_only(grid, x, args.repeats, backward_mode=mode)
        rows.append((f"cpp, backward_mode={mode}", f"{enc:.2f}", "-"))
        print(rows[-1], flush=True)
    for dtype in (torch.float16, torch.bfloat16):
        grid = HashGrid(**CONFIG, backend="cpp", dtype=dtype)
        rows.append(
            (
                f"cpp, {dtype}",
                f"{encoding_only(grid, x, args.repeats):.2f}",
                f"{step_proxy(grid, x, args.repeats):.2f}",
            )
        )
        print(rows[-1], flush=True)
    header = "| backend | encoding fwd+bwd (ms) | step proxy (ms) |\n|---|---:|---:|\n"
    table = header + "".join(f"| {a} | {b} | {c} |\n" for a, b, c in rows)
    text = (
        f"# Hash encoding speed\n\n{N} points, L=16 F=2 T=2^13 n_min=16 n_max=2048, "
        f"torch {torch.__version__}, {torch.get_num_threads()} threads; median of "
        f"{args.repeats} repeats after 5 warm-up calls.\n"
        "Step proxy = encoding + density MLP 32->64->16 + colour MLP 31->64->64->3 (bias-free, "
        "ReLU) + MSE + backward + fused Adam.\n\n"
        f"Command: `.venv/bin/python benchmarks/hashgrid_speed.py --repeats {args.repeats}`\n\n"
        + table
    )
    print(table)
    out = REPO / "benchmarks" / "results" / "hashgrid_speed.md"
    out.write_text(text)
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
