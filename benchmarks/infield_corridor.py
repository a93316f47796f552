"""Full-length results on the simulated in-field corridor (issue 8's "results users ask for").

Runs the `demo` pipeline of pipelines.yaml at full length: a 600-frame (20 s) simulated
nano-drone corridor flight -> ingest -> COLMAP -> every 8th kept frame held out for test (as in
the paper's in-field dataset) -> Tiny-DroNeRF with the gray head, 10k steps. Prints and writes
pose accuracy against the simulator's ground truth, test PSNR/SSIM, and time per stage.

    .venv/bin/python benchmarks/infield_corridor.py [--frames 600] [--steps 10000] [--work DIR]

The pipeline's cache makes a re-run after an interruption continue where it stopped.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from dronecap import cli
from dronecap.pipeline import read_stamp

STAGES = ("simulate", "ingest", "sfm", "split", "train")
OUT = Path(__file__).parent / "results" / "infield_corridor.md"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=600)
    ap.add_argument("--steps", type=int, default=10_000)
    ap.add_argument("--work", type=Path, default=Path("/tmp/dronecap-infield"))
    ap.add_argument("overrides", nargs="*", help="more pipeline overrides, e.g. train.grid_res=64")
    args = ap.parse_args()
    args.work.mkdir(parents=True, exist_ok=True)
    overrides = [f"frames={args.frames}", f"steps={args.steps}", *args.overrides]
    code = cli.main(["run", "demo", *overrides, "--until", "train", "--workdir", str(args.work)])
    if code != 0:
        raise SystemExit(code)
    runs = args.work / "runs" / "demo"
    sfm = json.loads((runs / "sfm" / "sfm" / "report.json").read_text())
    metrics = json.loads((runs / "train" / "runs" / "train" / "metrics.json").read_text())
    acc, test = sfm["accuracy"], metrics["test"]
    lines = [
        "# Simulated in-field corridor, full length",
        "",
        f"Command: `.venv/bin/python benchmarks/infield_corridor.py --frames {args.frames}"
        f" --steps {args.steps} {' '.join(args.overrides)}` (pipeline `demo`; gray head, preset"
        " tiny-dronerf, every 8th kept frame held out for test).",
        "",
        "| figure | value | paper (real corridor) |",
        "|---|---|---|",
        f"| frames: simulated / kept by ingest | {args.frames} / {sfm['frames_total']} | 1954 |",
        f"| registered by COLMAP | {sfm['registered']} ({sfm['registration_rate']:.1%}) | – |",
        f"| ATE after similarity alignment | {acc['ate_percent']:.2f}% of extent"
        f" ({acc['ate_rmse']:.4f} of {acc['extent']:.2f} m) | – |",
        f"| rotation error median / max | {acc['rot_median_deg']:.2f}°"
        f" / {acc['rot_max_deg']:.2f}° | – |",
        f"| test views | {test['views']} | 245 |",
        f"| test PSNR | {test['psnr']:.2f} dB | 21.2 dB |",
        f"| test SSIM | {test['ssim']:.3f} | 0.73 |",
        f"| training | {metrics['steps']} steps, {metrics['ms_per_step_median']:.1f} ms/step median"
        f" ({metrics['threads']} threads) | – |",
        "",
        "| stage | seconds |",
        "|---|---|",
    ]
    lines += [f"| {s} | {read_stamp(runs / s)['seconds']:.1f} |" for s in STAGES]
    text = "\n".join(lines) + "\n"
    print(text)
    OUT.parent.mkdir(parents=True, exist_ok=True)
    OUT.write_text(text)
    print(f"wrote {OUT}")


if __name__ == "__main__":
    main()
