"""The far field (issue 30 item 2): default ``dronecap train`` with the far field on and off.

Scenes (posed, split datasets; paths given with ``--scene NAME=PATH``):

- **himax**: the real Himax HM01B0 sequence test_23 (``ingest`` + ``sfm`` + ``split`` of
  ../shared/data/himax_hm01b0/test_23, as benchmarks/real_footage.py makes it);
- **object**: the one-sided lego object capture of benchmarks/imports_bounds.py (composited on
  white, no alpha, imported from a transforms.json without points);
- **lego**: lego 160 px with alpha (the resolver keeps the box only: must be unchanged);
- **corridor**: the simulated corridor (``dronecap simulate`` default, ``ingest``, ``sfm``,
  ``split``).

Each scene is trained with every ``--variants`` value of ``far_field`` (``none`` = the fixed
background as before; ``auto`` = what the resolver picks; or a kind, ``sh``/``grid``; or
settings ``FIELD=VALUE[,FIELD=VALUE]``, e.g. ``far_init=0.05``) and ``--seeds`` for
``--steps`` on 1 thread, into ``WORK/<scene>_<variant>``; a finished run there is reused (runs
can be started side by side with the CLI, then tabulated here). ``WORK/<scene>_<variant>.load``,
when present, holds the load averages at the run's start and end (one line each). The table
gives the resolved far field, test PSNR / SSIM, median ms/step and the load; the figure the
PSNR per scene and the learned far field of each run that has one (equirectangular, azimuth
across, +z up).

Usage: ``nice -n 10 .venv/bin/python benchmarks/far_field.py --work /tmp/ff30 --scene
himax=/tmp/scenes/h23/dataset.h5 --scene corridor=... --variants none sh``
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
RESULTS = REPO / "benchmarks" / "results"


def train(dataset: Path, run: Path, variant: str, steps: int, seed: int = 0) -> dict:
    """Default ``dronecap train`` with ``far_field=variant`` (unless "auto"; a variant with
    "=" is a comma-separated list of FIELD=VALUE settings instead) and training
    ``seed`` (unless 0, the default) for ``steps`` on 1 thread, reused when ``run`` finished
    it; the row of the table."""
    load = run.with_suffix(".load")
    if not (run / "metrics.json").exists():
        load.write_text(" ".join(f"{x:.2f}" for x in os.getloadavg()) + "\n")
        items = variant.split(",") if "=" in variant else [f"far_field={variant}"]
        sets = [a for item in items if item != "far_field=auto" for a in ("--set", item)]
        sets += ["--set", f"seed={seed}"] if seed else []
        env = {**os.environ, "PYTHONPATH": str(REPO), "OMP_NUM_THREADS": "1"}
        cmd = [sys.executable, "-m", "dronecap.cli", "train", str(dataset), "--steps", str(steps),
               "--out", str(run), "--threads", "1", "--no-progress", *sets]  # fmt: skip
        r = subprocess.run(cmd, env=env, cwd=REPO, capture_output=True, text=True)
        if r.returncode:
            raise SystemExit(f"{' '.join(cmd)} failed:\n{r.stderr[-2000:]}")
        with load.open("a") as f:
            f.write(" ".join(f"{x:.2f}" for x in os.getloadavg()) + "\n")
    m = json.loads((run / "metrics.json").read_text())
    loads = load.read_text().split("\n") if load.exists() else []
    return {
        "seed": m["config"]["seed"],
        "far_field": m["config"].get("far_field", "none"),
        "why": m["reasons"].get("far_field", ""),
        "steps": m["steps"],
        "psnr": m["test"]["psnr"],
        "ssim": m["test"]["ssim"],
        "ms": m["ms_per_step_median"],
        "load": " -> ".join(line.split()[0] for line in loads if line.strip()),
        "run": run,
    }


def far_map(run: Path) -> np.ndarray | None:
    """The learned far field of ``run`` as an image [rows, 2 rows, C] (None without one)."""
    from dronecap.nerf.far_field import environment_map
    from dronecap.nerf.trainer import Trainer

    far = Trainer.load(run / "checkpoint.pt").field.far
    return None if far is None else environment_map(far)


def figure(table: list[dict], path: Path) -> None:
    """PSNR per scene and variant, and the learned far fields."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    maps = [(r, far_map(r["run"])) for r in table if r["far_field"] != "none"]
    maps = [(r, m) for r, m in maps if m is not None]
    fig, axes = plt.subplots(1, 1 + len(maps), figsize=(5 + 4 * len(maps), 4), squeeze=False)
    ax = axes[0][0]
    scenes = list(dict.fromkeys(r["scene"] for r in table))
    variants = list(dict.fromkeys(r["variant"] for r in table))
    width = 0.8 / len(variants)
    for i, v in enumerate(variants):
        xs = [scenes.index(r["scene"]) + i * width for r in table if r["variant"] == v]
        ys = [r["psnr"] for r in table if r["variant"] == v]
        ax.bar(xs, ys, width, label=f"far_field={v}")
        for x, y in zip(xs, ys, strict=True):
            ax.text(x, y + 0.2, f"{y:.1f}", ha="center", fontsize=7)
    ax.set_xticks([i + 0.4 - width / 2 for i in range(len(scenes))], scenes)
    ax.set_ylabel("test PSNR (dB)")
    ax.legend(fontsize=7)
    for ax, (r, m) in zip(axes[0][1:], maps, strict=True):
        ax.imshow(m[..., 0] if m.shape[-1] == 1 else m, cmap="gray", vmin=0, vmax=1,
                  extent=(-180, 180, -90, 90))  # fmt: skip
        ax.set_title(f"{r['scene']}: far field ({r['far_field']})", fontsize=9)
        ax.set_xlabel("azimuth (deg)")
        ax.set_ylabel("elevation (deg)")
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--work", type=Path, required=True)
    p.add_argument("--scene", action="append", required=True, help="NAME=DATASET.h5")
    p.add_argument("--variants", nargs="+", default=["none", "auto"])
    p.add_argument("--steps", type=int, default=1500)
    p.add_argument("--seeds", type=int, nargs="+", default=[0], help="training seeds")
    p.add_argument("--no-train", action="store_true", help="tabulate finished runs only")
    args = p.parse_args()
    args.work.mkdir(parents=True, exist_ok=True)
    table = []
    for item in args.scene:
        name, path = item.split("=", 1)
        for seed in args.seeds:
            for v in args.variants:
                tag = v.replace("=", "").replace(",", "_")
                run = args.work / (f"{name}_{tag}" + (f"_s{seed}" if seed else ""))
                if args.no_train and not (run / "metrics.json").exists():
                    continue
                row = {"scene": name, "variant": v, **train(Path(path), run, v, args.steps, seed)}
                table.append(row)
                print(name, v, seed, row["far_field"], f"{row['psnr']:.2f} dB", flush=True)
    RESULTS.mkdir(exist_ok=True)
    figure(table, RESULTS / "far_field.png")
    lines = [
        "| scene | seed | far_field asked | resolved | test PSNR dB | SSIM | ms/step (median) "
        "| load (start -> end) |",
        "|---|---:|---|---|---:|---:|---:|---|",
    ]
    for r in table:
        lines.append(
            f"| {r['scene']} | {r['seed']} | {r['variant']} | {r['far_field']} | "
            f"{r['psnr']:.2f} | {r['ssim']:.3f} | {r['ms']:.0f} | {r['load']} |"
        )
    scenes = " ".join(f"--scene {item}" for item in args.scene)
    text = (
        "# The far field: default `dronecap train` with the far field on and off\n\n"
        f"Command: `nice -n 10 .venv/bin/python benchmarks/far_field.py --work {args.work} "
        f"{scenes} --variants {' '.join(args.variants)} --steps {args.steps} --seeds "
        f"{' '.join(map(str, args.seeds))}` (1 thread per "
        "run; finished runs reused).\n\n" + "\n".join(lines) + "\n\nFigure: `far_field.png`.\n"
    )
    print(text)
    out = RESULTS / "far_field.md"
    old = out.read_text() if out.exists() else ""
    notes = old[old.index("\n## Notes") :] if "\n## Notes" in old else ""  # kept when re-run
    out.write_text(text + notes)


if __name__ == "__main__":
    main()
