"""Drone capture folders: are the stream defects and the lost frames found exactly?

For each format (NanoCockpit, PULP-Dronet) simulates a corridor flight through a lossy link
(``dronecap simulate --format F --frames N --drop 0.05 --duplicate 0.03 --torn 0.03``), runs the
default ``dronecap ingest FOLDER`` and compares with the ground truth in ``flight.json``
(``stream.dropped / duplicated / torn``): camera frames found lost, torn and frozen frames, plus
how far the telemetry priors are from the true camera poses. Prints and writes
``benchmarks/results/capture_defects.md``.

    OMP_NUM_THREADS=1 nice .venv/bin/python benchmarks/capture_defects.py [--frames 240]
"""

from __future__ import annotations

import argparse
import json
import subprocess
import tempfile
import time
from pathlib import Path

import numpy as np

from dronecap.capture.selection import REASONS
from dronecap.cli import main
from dronecap.datasets import open_dataset

RESULTS = Path(__file__).resolve().parent / "results" / "capture_defects.md"
LINK = ["--drop", "0.05", "--duplicate", "0.03", "--torn", "0.03"]


def found(truth: list[int], got: list[int]) -> str:
    """'n/n exact', or what was missed and what was wrongly flagged."""
    t, g = set(truth), set(got)
    if t == g:
        return f"{len(t)}/{len(t)} exact"
    return f"{len(t & g)}/{len(t)}, missed {sorted(t - g)}, extra {sorted(g - t)}"


def run(fmt: str, frames: int, work: Path) -> dict[str, str]:
    folder = work / fmt
    args = ["-q", "simulate", "--format", fmt, "--frames", str(frames), "-o", str(folder), *LINK]
    assert main(args) == 0
    t0 = time.perf_counter()
    assert main(["-q", "ingest", str(folder), "--workdir", str(work / f"{fmt}_w")]) == 0
    seconds = time.perf_counter() - t0
    ds = open_dataset(work / f"{fmt}_w" / "frames.h5")
    doc = json.loads((folder / "flight.json").read_text())
    stream, gt_frames = doc["stream"], doc["frames"]
    camera = np.array([f["source_frame"] for f in gt_frames])  # of every delivered frame
    reason = ds.extra["reason"]
    torn = camera[reason == REASONS.index("torn")].tolist()
    frozen = camera[reason == REASONS.index("frozen")].tolist()
    gt = np.array([gt_frames[i]["c2w"] for i in ds.source_index])
    prior = ds.extra["prior_c2w"]
    pos = np.linalg.norm(gt[:, :3, 3] - prior[:, :3, 3], axis=1)
    rel = np.einsum("nji,njk->nik", gt[:, :3, :3], prior[:, :3, :3])
    cos = np.clip((np.trace(rel, axis1=1, axis2=2) - 1.0) / 2.0, -1.0, 1.0)
    ang = np.degrees(np.arccos(cos))
    return {
        "format": fmt,
        "delivered / kept": f"{len(reason)} / {ds.n}",
        "lost camera frames": found(stream["dropped"], ds.attrs["telemetry"]["dropped_frames"]),
        "torn": found(stream["torn"], torn),
        "duplicated (frozen)": found(stream["duplicated"], frozen),
        "priors matched": f"{int(ds.attrs['telemetry']['matched'])}/{len(reason)}",
        "prior error median (cm / deg)": f"{100 * np.median(pos):.1f} / {np.median(ang):.2f}",
        "ingest s": f"{seconds:.1f}",
    }


def main_cli() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=240, help="source frames per flight")
    args = ap.parse_args()
    load = subprocess.run(["uptime"], capture_output=True, text=True).stdout.strip()
    with tempfile.TemporaryDirectory() as tmp:
        rows = [run(fmt, args.frames, Path(tmp)) for fmt in ("nanocockpit", "pulp-dronet")]
    cols = list(rows[0])
    table = "| " + " | ".join(cols) + " |\n|" + "---|" * len(cols) + "\n"
    table += "".join("| " + " | ".join(r[c] for c in cols) + " |\n" for r in rows)
    text = (
        "# Drone capture folders: stream defects and lost frames found by `dronecap ingest`\n\n"
        f"Command: `OMP_NUM_THREADS=1 nice .venv/bin/python benchmarks/capture_defects.py "
        f"--frames {args.frames}` (simulate {' '.join(LINK)}, corridor, seed 0)\n\n"
        f"Load: `{load}`\n\n{table}\n"
        "Prior error: the telemetry pose (the simulated onboard estimate: noise, odometry scale "
        "and heading drift) against the true camera pose, over the kept frames.\n"
    )
    print(text)
    RESULTS.write_text(text)


if __name__ == "__main__":
    main_cli()
