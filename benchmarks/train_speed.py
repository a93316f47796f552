"""Trainer speed of the default configuration: step time against earlier code, render time.

Step time: everything `Trainer.train_step` does (drawing rays, marching, the occupancy grid
update when due, forward, backward, Adam) for the default ``scene-sized`` model on lego 160 px
RGB, resolved as ``dronecap train`` resolves it, after --warm steps (1100: past the grid's
all-cell warm-up and its growing update interval), in windows of --window steps (64: four of
the default's every-16-steps grid updates each), at 1 and 2 threads. Each variant runs in
its own process, and the variants take turns for --rounds rounds (the machine is shared: the
median over rounds of the median over windows):

- this commit;
- this commit with the MLPs multiplying in fp32 (``mlp_dtype=fp32``; the default "auto"
  multiplies in bf16 on a CPU with AMX-BF16 tiles);
- this commit with the hash-grid kernels built without their AVX2/AVX-512 paths
  (``DRONECAP_NO_SIMD=1``);
- earlier code (``--previous COMMIT``, default: the commit before this session's speed work),
  run from a ``git archive`` of that commit;
- the pure-PyTorch reference path (``--backend torch``: encoding and marching in PyTorch);
- the paper's preset (``tiny-dronerf``) on this commit, for reference.

Render time: one 160x160 view of models trained --trained steps (default 10000, 2 threads) on
lego and on the simulated corridor flight (``simulate -> ingest -> sfm -> split``), with the
default early stop and without it (the exact reference, PSNR between the two), at 1 and 2
threads; and the half-resolution preview.

    .venv/bin/python benchmarks/train_speed.py [--rounds 3] [--trained 10000]
    .venv/bin/python benchmarks/train_speed.py --only this,fp32 --rounds 6   # steps only

Writes benchmarks/results/train_speed.md (with the load average: measure on an idle machine).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
from _runs import write_page
from scene_sized import build_scene
from snapshot import DATA, RESULTS, unpack

LEGO = DATA / "nerf_synthetic_160" / "lego"
PREVIOUS = "b11b22b"  # main before the AVX2 kernel path, fused Adam and per-ray SH
ROW = "@@ "  # prefix of a measurement line printed by a --measure process


def lego(cache: Path):
    """The lego 160 px RGB dataset (imported once into ``cache``)."""
    from dronecap.datasets.blender import import_blender
    from dronecap.datasets.format import open_dataset

    path = cache / "lego.h5"
    if not path.exists():
        cache.mkdir(parents=True, exist_ok=True)
        import_blender(LEGO, path, progress=False)
    return open_dataset(path)


def as_trained(cfg, ds):
    """``cfg`` resolved against ``ds`` as ``dronecap train`` resolves it: a sized config's hash
    table sized within the GAP9 memory budget (without it, lego keeps 2^13 rows, not the
    default's 2^14, and steps ~15 % faster than the default really takes)."""
    from dronecap.nerf.resolve import resolve

    try:
        from dronecap.gap9.model import memory_bytes
    except ImportError:  # --previous code, from before gap9.model.memory_bytes
        from dronecap.gap9.model import cost_report

        def memory_bytes(c):
            return cost_report(c)["memory"]["untiled"]["total"]

    return resolve(cfg, ds, memory_fn=memory_bytes)


def measure_steps(args: argparse.Namespace) -> None:
    """(--measure) Train --warm steps, then print one JSON row per thread count: median CPU
    and wall ms per step over --repeats windows of --window steps."""
    import torch

    from dronecap.nerf.config import preset
    from dronecap.nerf.trainer import Trainer

    torch.set_num_threads(1)
    ds = lego(Path(args.cache))
    cfg = preset(args.preset)
    if args.mlp_dtype:  # not given to --previous code, which has no such field
        cfg = cfg.replace(mlp_dtype=args.mlp_dtype)
    tr = Trainer(as_trained(cfg, ds), ds, backend=args.backend)
    tr.train(args.warm)
    for threads in (1, 2):
        torch.set_num_threads(threads)
        tr.train(4)
        wall, cpu, logs = [], [], []
        for _ in range(args.repeats):
            t0, c0 = time.perf_counter(), time.process_time()
            logs = tr.train(args.window)
            wall.append(1000 * (time.perf_counter() - t0) / args.window)
            cpu.append(1000 * (time.process_time() - c0) / args.window)
        samples = float(np.mean([lg["samples"] for lg in logs]))
        rays = float(np.mean([lg["rays"] for lg in logs]))
        row = dict(threads=threads, cpu_ms=float(np.median(cpu)), wall_ms=float(np.median(wall)),
                   samples=samples, per_ray=samples / rays,
                   code=str(Path(sys.modules["dronecap"].__file__).parent))  # fmt: skip
        print(ROW + json.dumps(row), flush=True)


def run_variant(args: argparse.Namespace, extra: list[str], env: dict[str, str]) -> list[dict]:
    """Run this script with --measure (plus ``extra``) in a new process with ``env`` added."""
    cmd = [sys.executable, str(Path(__file__).resolve()), "--measure", "--warm", str(args.warm),
           "--window", str(args.window), "--repeats", str(args.repeats), "--cache", args.cache,
           *extra]  # fmt: skip
    # not in the repository: `python script` puts the script's folder first on sys.path, never
    # the repository root, so a PYTHONPATH snapshot is what `import dronecap` finds
    p = subprocess.run(cmd, env=dict(os.environ, **env), capture_output=True, text=True,
                       cwd=args.cache)  # fmt: skip
    if p.returncode != 0:
        raise SystemExit(f"variant {extra} {env} failed: {p.stderr.strip()[-400:]}")
    rows = [json.loads(line[len(ROW) :]) for line in p.stdout.splitlines() if line.startswith(ROW)]
    want = env.get("PYTHONPATH")  # an editable install must not shadow the code asked for
    if want and not all(r["code"].startswith(want) for r in rows):
        raise SystemExit(f"variant {env} imported dronecap from {rows[0]['code']}, not {want}")
    return rows


def render_rows(args: argparse.Namespace, name: str, ds) -> list[tuple[str, str, str, str]]:
    """Train the default model --trained steps on ``ds`` (2 threads; kept in --cache for the
    next run) and time its renders."""
    import torch

    from dronecap.nerf.config import preset
    from dronecap.nerf.trainer import Trainer

    torch.set_num_threads(2)
    saved = Path(args.cache) / f"render-{name}-{args.trained}.ckpt"  # trained once, then reused
    if saved.exists():
        tr = Trainer.load(saved, train=ds)
    else:
        tr = Trainer(as_trained(preset("scene-sized").replace(steps=args.trained), ds), ds)
        tr.train(args.trained)
        tr.save(saved)
    views = np.flatnonzero(ds.split == 2)
    views = views[:: max(1, len(views) // 5)][:5]
    rows, exact = [], None
    variants = [("no early stop (exact)", 1, dict(min_transmittance=0.0, min_weight=0.0)),
                ("default", 1, {}), ("default", 2, {})]  # fmt: skip
    for label, threads, thresholds in variants:
        torch.set_num_threads(threads)
        wall, cpu, images = [], [], []
        for _ in range(args.repeats):
            images = []
            for i in views:
                t0, c0 = time.perf_counter(), time.process_time()
                images.append(tr.render(ds.poses[i], ds.intrinsics, **thresholds))
                wall.append(1000 * (time.perf_counter() - t0))
                cpu.append(1000 * (time.process_time() - c0))
        if exact is None:
            exact, note = np.stack(images), "the reference"
        else:
            mse = float(np.mean((np.stack(images) - exact) ** 2))
            note = f"{-10 * np.log10(max(mse, 1e-20)):.0f} dB from the reference"
        rows.append((f"render, {name}, {args.trained}-step model, {label}, {threads} thread(s)",
                     f"{np.median(cpu):.0f}", f"{np.median(wall):.0f}",
                     f"{len(views)} views x {args.repeats}; {note}"))  # fmt: skip
        print(rows[-1], flush=True)
    return rows


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--warm", type=int, default=1100, help="steps trained before timing")
    p.add_argument("--window", type=int, default=64, help="steps per timed window")
    p.add_argument("--repeats", type=int, default=3, help="timed windows (renders: passes)")
    p.add_argument("--rounds", type=int, default=3, help="turns each step variant takes")
    p.add_argument("--previous", default=PREVIOUS, help="earlier commit to compare with")
    p.add_argument("--trained", type=int, default=10_000, help="steps of the render models")
    p.add_argument("--cache", default="/tmp/dronecap_bench")
    p.add_argument("--measure", action="store_true", help=argparse.SUPPRESS)
    p.add_argument("--preset", default="scene-sized", help=argparse.SUPPRESS)
    p.add_argument("--backend", default="auto", help=argparse.SUPPRESS)
    p.add_argument("--mlp-dtype", default=None, help=argparse.SUPPRESS)
    p.add_argument(
        "--only",
        default="",
        help="comma-separated step variants (this, fp32, nosimd, previous, torch, paper): "
        "more rounds of a few, no renders; writes train_speed_steps.md",
    )
    args = p.parse_args()
    Path(args.cache).mkdir(parents=True, exist_ok=True)
    if args.measure:
        measure_steps(args)
        return
    import torch

    lego(Path(args.cache))  # imported once, before the variants run
    old = unpack(args.previous, Path(args.cache))
    variants = {
        "this": ("this commit", [], {}),
        "fp32": ("this commit, fp32 MLP products", ["--mlp-dtype", "fp32"], {}),
        "nosimd": ("this commit, kernels without SIMD", [], {"DRONECAP_NO_SIMD": "1"}),
        "previous": (f"previous code ({args.previous})", [], {"PYTHONPATH": str(old)}),
        "torch": ("PyTorch reference path", ["--backend", "torch"], {}),
        "paper": ("paper preset (tiny-dronerf), this commit", ["--preset", "tiny-dronerf"], {}),
    }
    only = args.only.split(",") if args.only else list(variants)
    if unknown := sorted(set(only) - set(variants)):
        raise SystemExit(f"unknown variants {unknown}; known: {', '.join(variants)}")
    variants = {variants[k][0]: variants[k][1:] for k in only}
    got: dict[tuple[str, int], list[dict]] = {}
    for r in range(args.rounds):
        for name, (extra, env) in variants.items():
            for row in run_variant(args, extra, env):
                got.setdefault((name, row["threads"]), []).append(row)
                print(f"round {r + 1}: {name}: {row}", flush=True)
    rows = []
    for (name, threads), rs in got.items():
        cpu = float(np.median([x["cpu_ms"] for x in rs]))
        wall = float(np.median([x["wall_ms"] for x in rs]))
        batch = f"{rs[-1]['samples']:.0f} samples, {rs[-1]['per_ray']:.1f}/ray"
        if len(rs) > 2:  # the spread a median of two hides
            batch += "; rounds " + " / ".join(f"{x['wall_ms']:.1f}" for x in rs) + " ms"
        rows.append((f"step, {name}, {threads} thread(s)", f"{cpu:.1f}", f"{wall:.1f}", batch))
    rows.sort(key=lambda r: ("2 thread" in r[0], r[0]))
    if not args.only:
        from dronecap.datasets.format import open_dataset

        rows += render_rows(args, "lego", lego(Path(args.cache)))
        work = Path(args.cache) / "scenes"
        rows += render_rows(args, "corridor", open_dataset(build_scene("corridor", work)))
    load = " ".join(f"{x:.1f}" for x in os.getloadavg())
    lines = [
        "# Trainer speed (default scene-sized model)",
        "",
        f"torch {torch.__version__}; steps: lego 160 px RGB after {args.warm} warm-up steps, "
        f"median over {args.rounds} rounds (variants in turn, each in its own process) of the "
        f"median of {args.repeats} windows of {args.window} steps, grid updates included. "
        "Renders: one 160x160 test view, median over 5 views x "
        f"{args.repeats}, default early stop (transmittance < 1e-3, colour skipped for weights "
        f"< 1e-4) against none. Load average (1/5/15 min) at the end: {load} (2 cores; CPU ms "
        "of a 1-thread row is what it costs on an idle core, wall ms of a 2-thread row is "
        "only meaningful at a load near 0).",
        "",
        f"Command: `.venv/bin/python benchmarks/train_speed.py --rounds {args.rounds}"
        + (f" --only {args.only}`" if args.only else "`"),
        "",
        "| measurement | CPU ms | wall ms | batch / note |",
        "|---|---:|---:|---|",
        *[f"| {a} | {b} | {c} | {d} |" for a, b, c, d in rows],
    ]
    write_page(lines, RESULTS / ("train_speed_steps.md" if args.only else "train_speed.md"))


if __name__ == "__main__":
    main()
