"""The default model sized to each scene, against the paper's preset and the largest Table II row.

Every scene the project has is trained with the same step count under three configurations:

- ``scene-sized`` (the default of ``dronecap train``): n_max, marching step, occupancy grid and
  hash-table size resolved from the dataset within the GAP9 budget (nerf/sizing.py);
- ``tiny-dronerf``: the paper's deployed row as published (N_max 2048, 128^3 grid, T = 2^13);
- ``b32k-t14``: the largest Tiny-DroNeRF row of Table II (32768 samples per step, T = 2^14).

Scenes: lego 160 px RGB and gray (NeRF Synthetic), the simulated corridor flight
(``simulate -> ingest -> sfm -> split``), a degraded simulated flight (``simulate --sensor
aideck``: 324x244 HM01B0 lens, noise, vignetting, exposure drift, Wi-Fi losses) and a real
Himax HM01B0 sequence (test_23, ``ingest -> sfm -> split``). Per run: test PSNR/SSIM over all
test views, the modelled GAP9 memory (``cost.json``), the process time of the training steps
and ms/step (1 thread), and what the sizing chose. Each run is one ``dronecap train`` in its own
folder; finished runs are not re-run (delete a folder to redo it).

    nice .venv/bin/python benchmarks/scene_sized.py [--steps 3000] [--scenes lego,corridor]
        [--work /tmp/dronecap-scene-sized] [--snapshot]

Writes benchmarks/results/scene_sized.md and scene_sized.png.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

from snapshot import DATA, RESULTS, dronecap_command, rerun_on_snapshot

LEGO = DATA / "nerf_synthetic_160" / "lego"
HIMAX = DATA / "himax_hm01b0" / "test_23"
CONFIGS = ("scene-sized", "tiny-dronerf", "b32k-t14")
# scene -> commands that build <scene folder>/dataset.h5 (each runs with --workdir there)
SCENES: dict[str, list[list[str]]] = {
    "lego": [["import-blender", str(LEGO), "--color", "rgb"]],
    "lego-gray": [["import-blender", str(LEGO), "--color", "gray"]],
    "corridor": [
        ["simulate", "--scene", "corridor", "--frames", "240", "--seed", "0"],
        ["ingest", "flight.mp4"],
        ["sfm", "--gt", "flight.json"],
        ["split"],
    ],
    "aideck-flight": [
        ["simulate", "--scene", "corridor", "--frames", "240", "--seed", "0", "--sensor", "aideck"],
        ["ingest", "flight.mp4"],
        ["sfm", "--gt", "flight.json"],
        ["split"],
    ],
    "himax-test_23": [["ingest", str(HIMAX)], ["sfm"], ["split"]],
}


def build_scene(name: str, work: Path) -> Path:
    """``work/name/dataset.h5``, built by the scene's commands unless it exists."""
    folder = work / name
    dataset = folder / "dataset.h5"
    if not dataset.exists():
        folder.mkdir(parents=True, exist_ok=True)
        for args in SCENES[name]:
            dronecap_command([*args, "--workdir", str(folder)], folder / "log.txt", cwd=folder)
    return dataset


def train_run(
    dataset: Path, config: str, steps: int, run: Path, sets: tuple[str, ...] = ()
) -> dict:
    """Train ``config`` (with ``--set`` assignments ``sets``) on ``dataset`` for ``steps``
    (1 thread) into ``run``; its record."""
    if not (run / "metrics.json").exists():
        run.parent.mkdir(parents=True, exist_ok=True)
        args = ["train", str(dataset), "--preset", config, "--steps", str(steps), "--threads",
                "1", "--no-progress", "--out", str(run)]  # fmt: skip
        args += [a for s in sets for a in ("--set", s)]
        dronecap_command(args, run.parent / f"{run.name}.log")
    metrics = json.loads((run / "metrics.json").read_text())
    cost = json.loads((run / "cost.json").read_text())
    cfg = metrics["config"]
    return {
        "config": config,
        "psnr": metrics["test"]["psnr"],
        "ssim": metrics["test"]["ssim"],
        "views": metrics["test"]["views"],
        "gap9_mb": cost["memory"]["untiled"]["total"] / 1e6,
        "train_s": metrics["train_seconds"],
        "ms_step": metrics["ms_per_step_median"],
        "model": f"{cfg['n_max']} / {cfg['march_steps']} / {cfg['grid_res']} / "
        f"{cfg['log2_hashmap']} / {cfg['channels']}",
    }


def ms_text(ms: float | None) -> str:
    """ms/step for the table ('–': a resumed run that timed no step of its own)."""
    return "–" if ms is None else f"{ms:.1f}"


def table(rows: list[dict], steps: int, load: str) -> str:
    """The results page (markdown)."""
    lines = [
        "# The default model sized to the scene (benchmarks/scene_sized.py)",
        "",
        f"{steps} steps per run, 1 torch thread, test PSNR/SSIM over all test views of each "
        "scene (scikit-image), GAP9 memory from the run's `cost.json` (the model that was "
        "trained, untiled). Train s is the wall time of the optimizer steps and ms/step their "
        f"median, under the load of the shared 2-core machine ({load}): compare the rows of one "
        "scene, not absolute times. `model` is n_max / march steps / occupancy grid / log2 T / "
        "channels as resolved for that scene.",
        "",
        f"Command: `nice .venv/bin/python benchmarks/scene_sized.py --steps {steps}`",
        "",
        "| scene | config | PSNR dB | SSIM | views | GAP9 MB | train s | ms/step | model |",
        "|---|---|---:|---:|---:|---:|---:|---:|---|",
    ]
    for r in rows:
        if "error" in r:
            lines.append(f"| {r['scene']} | {r['config']} | failed: {r['error']} ||||||| |")
            continue
        lines.append(
            f"| {r['scene']} | {r['config']} | {r['psnr']:.2f} | {r['ssim']:.3f} | {r['views']} "
            f"| {r['gap9_mb']:.1f} | {r['train_s']:.0f} | {ms_text(r['ms_step'])} | {r['model']} |"
        )
    return "\n".join(lines) + "\n"


def plot(rows: list[dict], path: Path) -> None:
    """PSNR and GAP9 memory per scene, one bar per configuration."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    ok = [r for r in rows if "error" not in r]
    scenes = list(dict.fromkeys(r["scene"] for r in ok))
    fig, axes = plt.subplots(1, 2, figsize=(11, 3.8))
    width = 0.8 / len(CONFIGS)
    for i, config in enumerate(CONFIGS):
        by = {r["scene"]: r for r in ok if r["config"] == config}
        x = np.arange(len(scenes)) + (i - (len(CONFIGS) - 1) / 2) * width
        for ax, key in zip(axes, ("psnr", "gap9_mb"), strict=True):
            ax.bar(x, [by[s][key] if s in by else np.nan for s in scenes], width, label=config)
    for ax, label in zip(axes, ("test PSNR (dB)", "modelled GAP9 memory (MB)"), strict=True):
        ax.set_xticks(np.arange(len(scenes)), scenes, rotation=20)
        ax.set_ylabel(label)
    axes[1].axhline(21.0, color="k", lw=0.8, ls="--", label="paper's 21 MB")
    axes[0].set_ylim(bottom=min([r["psnr"] for r in ok], default=0) - 3)
    axes[1].legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--steps", type=int, default=3000)
    ap.add_argument("--scenes", default=",".join(SCENES), help="comma-separated scene names")
    ap.add_argument("--configs", default=",".join(CONFIGS), help="comma-separated presets")
    ap.add_argument("--work", type=Path, default=Path("/tmp/dronecap-scene-sized"))
    ap.add_argument("--snapshot", action="store_true", help="run on the committed HEAD")
    ap.add_argument("--table-only", action="store_true", help="only the finished runs, no training")
    args = ap.parse_args()
    if args.snapshot:
        rerun_on_snapshot(args.work, Path(__file__))
    names = [s.strip() for s in args.scenes.split(",")]
    if unknown := [s for s in names if s not in SCENES]:
        raise SystemExit(f"unknown scenes {unknown}; known: {list(SCENES)}")
    rows = []
    configs = args.configs.split(",")
    for config in configs:  # every scene's default first, the largest row last
        for name in names:
            t0 = time.perf_counter()
            run = args.work / name / "runs" / f"{config}-{args.steps}"
            if args.table_only and not (run / "metrics.json").exists():
                continue
            try:
                dataset = build_scene(name, args.work)
                rec = train_run(dataset, config, args.steps, run)
            except RuntimeError as err:
                rec = {"config": config, "error": str(err)[:200]}
            rows.append({"scene": name, **rec})
            print(json.dumps(rows[-1]), f"({time.perf_counter() - t0:.0f} s)", flush=True)
    rows.sort(key=lambda r: (names.index(r["scene"]), configs.index(r["config"])))
    load = "load average " + " ".join(open("/proc/loadavg").read().split()[:3]) + " at the end"
    text = table(rows, args.steps, load)
    print(text)

    RESULTS.mkdir(exist_ok=True)
    (RESULTS / "scene_sized.md").write_text(text)
    plot(rows, RESULTS / "scene_sized.png")
    print(f"wrote {RESULTS / 'scene_sized'}.md/.png", file=sys.stderr)


if __name__ == "__main__":
    main()
