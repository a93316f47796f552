"""Trainer speed on lego 160 px: a full tiny-dronerf training step and one 160x160 render.

A "full step" is everything `Trainer.train_step` does: drawing rays, marching, the occupancy
grid update when due (amortised: steps are timed over a window that includes the steady
every-16-steps updates), forward/backward over the tiles, and Adam. The model is first trained
for --warm steps so that the grid, the samples per ray and the renders are representative.
Variants: thread counts, accumulation tiles of 1024 (as on GAP9) vs one 8192-sample tile,
the C++ kernels vs the PyTorch reference. Medians of --repeats windows.

    .venv/bin/python benchmarks/train_speed.py
"""

from __future__ import annotations

import argparse
import os
import time
from pathlib import Path

import numpy as np
import torch

REPO = Path(__file__).resolve().parents[1]
RESULTS = REPO / "benchmarks" / "results"
LEGO = REPO.parent / "shared" / "data" / "nerf_synthetic_160" / "lego"


def main() -> None:
    """Measure and write benchmarks/results/train_speed.md."""
    from dronecap.datasets.blender import import_blender
    from dronecap.datasets.format import open_dataset
    from dronecap.nerf.config import preset
    from dronecap.nerf.trainer import Trainer

    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--warm", type=int, default=500, help="steps trained before timing")
    p.add_argument("--trained", type=int, default=3000, help="steps of the second render model")
    p.add_argument("--window", type=int, default=32, help="steps per timed window")
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--cache", default="/tmp/dronecap_bench")
    args = p.parse_args()
    path = Path(args.cache) / "lego.h5"
    if not path.exists():
        import_blender(LEGO, path, progress=False)
    ds = open_dataset(path)
    torch.set_num_threads(1)
    base = preset("tiny-dronerf").replace(grid_res=64, tile_samples=8192)
    tr = Trainer(base, ds)
    tr.train(args.warm, progress=False)
    state = {k: v.clone() for k, v in tr.field.state_dict().items()}
    grid = tr.grid_state()
    rows = []

    def step_ms(label: str, threads: int, backend: str = "auto", **changes) -> None:
        torch.set_num_threads(threads)
        t = Trainer(base.replace(**changes), ds, backend=backend)
        t.field.load_state_dict(state)
        res = t.grid_cfg.res
        if res == base.grid_res:
            t.load_grid_state(grid)
        else:  # nearest-neighbour resampling of the warmed-up grid
            idx = np.arange(res) * base.grid_res // res
            cube = {k: v.reshape((base.grid_res,) * 3) for k, v in grid.items()}
            t.load_grid_state({k: v[np.ix_(idx, idx, idx)].reshape(-1) for k, v in cube.items()})
        t.step = tr.step  # after warm-up: updates every 16 steps
        t.samples_per_ray = tr.samples_per_ray
        t.train(4, progress=False)
        wall, cpu = [], []
        for _ in range(args.repeats):
            t0, c0 = time.perf_counter(), time.process_time()
            logs = t.train(args.window, progress=False)
            wall.append(1000 * (time.perf_counter() - t0) / args.window)
            cpu.append(1000 * (time.process_time() - c0) / args.window)
        spr = np.mean([lg["samples"] / lg["rays"] for lg in logs])
        batch = f"{np.mean([lg['samples'] for lg in logs]):.0f} samples, {spr:.1f}/ray"
        rows.append((label, f"{np.median(cpu):.1f}", f"{np.median(wall):.1f}", batch))
        print(rows[-1], flush=True)

    test = np.flatnonzero(ds.split == 2)[::40]
    exact: dict[str, np.ndarray] = {}

    def render_s(label: str, threads: int, **thresholds) -> None:
        """Median time of a view; with ``thresholds`` (render_rays' early-stop settings) the
        renders become the reference the default ones are compared with (PSNR between them)."""
        torch.set_num_threads(threads)
        wall, cpu, images = [], [], []
        for _ in range(args.repeats):
            images = []
            for i in test:
                t0, c0 = time.perf_counter(), time.process_time()
                images.append(tr.render(ds.poses[i], ds.intrinsics, **thresholds))
                wall.append(1000 * (time.perf_counter() - t0))
                cpu.append(1000 * (time.process_time() - c0))
        key = f"{tr.step}"
        if thresholds:
            exact[key] = np.stack(images)
            note = "the reference"
        elif key in exact:
            mse = float(np.mean((np.stack(images) - exact[key]) ** 2))
            note = f"{-10 * np.log10(max(mse, 1e-20)):.0f} dB from the reference"
        else:
            note = ""
        rows.append(
            (
                label,
                f"{np.median(cpu):.0f}",
                f"{np.median(wall):.0f}",
                f"{len(test)} views x {args.repeats}" + (f"; {note}" if note else ""),
            )
        )
        print(rows[-1], flush=True)

    step_ms("step, tiny-dronerf (grid 64^3), 1 tile of 8192, C++ kernels, 1 thread", 1)
    step_ms("step, 8 tiles of 1024 (GAP9 accumulation), 1 thread", 1, tile_samples=1024)
    step_ms("step, grid 128^3 (paper preset as is), 1 thread", 1, grid_res=128)
    step_ms("step, PyTorch reference encoding + marching, 1 thread", 1, backend="torch")
    step_ms("step, tiny-dronerf (grid 64^3), 1 tile of 8192, C++ kernels, 2 threads", 2)
    no_stop = dict(min_transmittance=0.0, min_weight=0.0)
    for steps in (args.warm, args.trained):  # a young foggy model, then a trained one
        torch.set_num_threads(1)
        tr.train(steps - tr.step, progress=False)
        at = f"{steps}-step model"
        render_s(f"render 160x160 view, {at}, no early stop (exact), 1 thread", 1, **no_stop)
        render_s(f"render 160x160 view, {at}, 1 thread", 1)
        render_s(f"render 160x160 view, {at}, 2 threads", 2)
    load = os.getloadavg()[0]
    lines = [
        "# Trainer speed (lego 160 px, tiny-dronerf)",
        "",
        f"torch {torch.__version__}, after {args.warm} warm-up steps; median of "
        f"{args.repeats} windows of {args.window} steps (grid updates included, amortised). "
        f"Load average {load:.1f} at the end of the run (2 cores): with other jobs running, "
        "wall-clock times are inflated and the process CPU time of a 1-thread run is what "
        "the step costs on an idle core. Renders: every 40th test view, the default early "
        "stop (transmittance < 1e-3, colour skipped for weights < 1e-4) against none.",
        "",
        "Command: `.venv/bin/python benchmarks/train_speed.py`",
        "",
        "| measurement | CPU ms | wall ms | batch |",
        "|---|---:|---:|---|",
        *[f"| {a} | {b} | {c} | {d} |" for a, b, c, d in rows],
    ]
    text = "\n".join(lines) + "\n"
    print(text)
    RESULTS.mkdir(parents=True, exist_ok=True)
    (RESULTS / "train_speed.md").write_text(text)


if __name__ == "__main__":
    main()
