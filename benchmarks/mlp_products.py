"""bf16 against fp32 MLP products: PSNR at equal steps over seeds, and the time they take.

The default ``mlp_dtype=auto`` multiplies the MLPs in bf16 on a CPU with native bf16 products
(AVX512-BF16, AMX); weights, gradients and Adam stay fp32. This benchmark is the evidence for
that default: the same ``dronecap train`` (default scene-sized model, 1 thread) with
``--set mlp_dtype=fp32`` and ``--set mlp_dtype=bf16``, for several seeds on lego 160 px RGB
and on the simulated corridor flight. The corridor's test PSNR moves by ±0.5 dB from seed to
seed at 3000 steps, so a single pair of runs says nothing: the table gives the mean and
standard deviation over seeds, and the mean paired difference with its standard error. The two
runs of a seed train side by side (one process each, same load), so their time ratio is fair.

    nice .venv/bin/python benchmarks/mlp_products.py [--steps 3000] [--seeds 8]
        [--scenes corridor,lego] [--work /tmp/dronecap-scene-sized]

Writes benchmarks/results/mlp_products.md. Finished runs are kept in --work and not re-run.
"""

from __future__ import annotations

import argparse
import json
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np
from scene_sized import build_scene, train_run
from snapshot import RESULTS

DTYPES = ("fp32", "bf16")


def run_pair(dataset: Path, folder: Path, steps: int, seed: int) -> dict[str, dict]:
    """The fp32 and bf16 runs of one seed, trained side by side: {dtype: record}."""
    with ThreadPoolExecutor(len(DTYPES)) as pool:
        jobs = {
            d: pool.submit(
                train_run,
                dataset,
                "scene-sized",
                steps,
                folder / f"mlp-{d}-s{seed}-{steps}",
                (f"mlp_dtype={d}", f"seed={seed}"),
            )  # fmt: skip
            for d in DTYPES
        }
        return {d: job.result() for d, job in jobs.items()}


def summary(scene: str, pairs: list[dict[str, dict]]) -> list[str]:
    """Table rows of one scene: per dtype mean ± sd of PSNR/SSIM and time, then the paired
    bf16 - fp32 difference."""
    rows = []
    for d in DTYPES:
        psnr = np.array([p[d]["psnr"] for p in pairs])
        ssim = np.array([p[d]["ssim"] for p in pairs])
        secs = np.array([p[d]["train_s"] for p in pairs])
        rows.append(
            f"| {scene} | {d} | {len(pairs)} | {psnr.mean():.2f} ± {psnr.std(ddof=1):.2f} | "
            f"{psnr.min():.2f} – {psnr.max():.2f} | {ssim.mean():.3f} | {np.median(secs):.0f} |"
        )
    diff = np.array([p["bf16"]["psnr"] - p["fp32"]["psnr"] for p in pairs])
    ratio = np.median([p["bf16"]["train_s"] / p["fp32"]["train_s"] for p in pairs])
    se = diff.std(ddof=1) / np.sqrt(len(diff))
    rows.append(
        f"| {scene} | bf16 − fp32 (paired) | {len(pairs)} | {diff.mean():+.2f} ± {se:.2f} (s.e.) "
        f"| {diff.min():+.2f} – {diff.max():+.2f} | | time × {ratio:.2f} |"
    )
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--steps", type=int, default=3000)
    ap.add_argument("--seeds", type=int, default=8)
    ap.add_argument("--scenes", default="corridor,lego")
    ap.add_argument("--work", type=Path, default=Path("/tmp/dronecap-scene-sized"))
    args = ap.parse_args()
    rows = []
    for scene in args.scenes.split(","):
        dataset = build_scene(scene, args.work)
        pairs = []
        for seed in range(args.seeds):
            pairs.append(run_pair(dataset, args.work / scene / "runs", args.steps, seed))
            print(scene, seed, json.dumps({d: round(r["psnr"], 3) for d, r in pairs[-1].items()}),
                  flush=True)  # fmt: skip
        rows += summary(scene, pairs)
    load = " ".join(open("/proc/loadavg").read().split()[:3])
    text = "\n".join([
        "# MLP products: bf16 against fp32 (benchmarks/mlp_products.py)",
        "",
        f"Default scene-sized model, {args.steps} steps, 1 thread per run, the two runs of a seed "
        "side by side; test PSNR/SSIM over all test views. PSNR is mean ± standard deviation "
        "over seeds; the paired row is the mean of the per-seed differences ± its standard "
        "error, and the median per-seed ratio of training time. Load average at the end: "
        f"{load} (2 cores).",
        "",
        f"Command: `nice .venv/bin/python benchmarks/mlp_products.py --steps {args.steps} "
        f"--seeds {args.seeds} --scenes {args.scenes}`",
        "",
        "| scene | MLP products | seeds | PSNR dB | range | SSIM | train s (median) |",
        "|---|---|---:|---:|---:|---:|---:|",
        *rows,
    ]) + "\n"  # fmt: skip
    print(text)
    RESULTS.mkdir(exist_ok=True)
    (RESULTS / "mlp_products.md").write_text(text)


if __name__ == "__main__":
    main()
