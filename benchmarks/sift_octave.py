"""SIFT's first octave for 160-px frames: -1 (2x upsampling) against -2 (4x), speed against error.

Every case of :mod:`real_footage` that has a reference or a floor (the Himax sequences, the white
lego orbit video with its Blender poses, the simulated drone capture folders with their flight's
ground truth) runs the default ``ingest`` and ``sfm --first-octave O`` for each octave, in its
own work folder, on a snapshot of HEAD; two cases at a time (one per core), each SfM on one
thread, so the two octaves of a case see the same machine. Prints and writes
``benchmarks/results/sift_octave.md``: registered %, reprojection error, keypoints per frame,
ATE, rotation error, sfm seconds and the remedy the retries used, per case and octave, and the
median ratio of the two octaves' sfm times. Usage::

    nice .venv/bin/python benchmarks/sift_octave.py [--work DIR] [--octaves -1 -2] [--only S ...]
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np
from real_footage import FLOORS, run_case, slug
from snapshot import RESULTS, rerun_on_snapshot

CASES = [  # test_23 before test_15 (camera of test_23) in each octave's folder
    "himax test_23",
    "himax test_10",
    "himax test_2",
    "himax test_15 (camera of test_23)",
    "lego orbit video",
    "sim nanocockpit, priors",
    "sim pulp-dronet, priors",
]


def one(name: str, octave: int, work: Path, n_sim: int) -> dict:
    """One case at one octave (reused when its row exists): the table row."""
    saved = work / f"octave{octave}" / (slug(name) + ".row.json")
    if saved.exists():
        return json.loads(saved.read_text())
    saved.parent.mkdir(parents=True, exist_ok=True)
    row = run_case(name, saved.parent, n_sim, ["--first-octave", str(octave)])
    report = saved.parent / slug(name) / "sfm" / "report.json"
    if report.exists():
        row["keypoints"] = json.loads(report.read_text()).get("keypoints_per_frame_median")
    row["octave"] = octave
    saved.write_text(json.dumps(row))
    print(json.dumps(row), flush=True)
    return row


def cell(row: dict, key: str, spec: str) -> str:
    v = row.get(key)
    return "–" if v is None else format(v, spec)


def table(rows: list[dict], octaves: list[int], load: str) -> str:
    """Markdown: one line per case and octave, then the median time ratio."""
    lines = [
        "# SIFT first octave on 160-px frames: -1 (2x upsampled) vs -2 (4x)",
        "",
        "Command: `nice .venv/bin/python benchmarks/sift_octave.py` (default `ingest`, then "
        "`sfm --threads 1 --first-octave O`; two cases at a time on the 2-core machine).",
        f"Load when it started: `{load}`",
        "",
        "| case | octave | registered | reproj. px | keypoints/frame | ATE % | rot. median ° "
        "| scale err. % | sfm s | remedy | floor (reg. %, ATE %, rot. °) |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    ratios = []
    for name in CASES:
        by = {r["octave"]: r for r in rows if r["case"] == name}
        for o in octaves:
            r = by.get(o)
            if r is None:
                continue
            if "error" in r:
                lines.append(f"| {name} | {o} | {r['error']} | | | | | | | | |")
                continue
            floor = FLOORS.get(name) or ()
            floor_text = " / ".join("–" if v is None else f"{v:g}" for v in floor[:3])
            lines.append(
                f"| {name} | {o} | {r['registered_pct']:.1f} % | {cell(r, 'reproj_px', '.3f')} "
                f"| {cell(r, 'keypoints', '.0f')} | {cell(r, 'ate_pct', '.3f')} "
                f"| {cell(r, 'rot_deg', '.2f')} | {cell(r, 'scale_err_pct', '.2f')} "
                f"| {r['seconds']:.0f} | {r['remedy'] or '–'} | {floor_text} |"
            )
        if len(octaves) == 2 and all(o in by and "error" not in by[o] for o in octaves):
            ratios.append(by[octaves[1]]["seconds"] / by[octaves[0]]["seconds"])
    if ratios:
        lines += [
            "",
            f"sfm time, octave {octaves[1]} / octave {octaves[0]}: median {np.median(ratios):.2f}x "
            f"over {len(ratios)} cases (range {min(ratios):.2f}-{max(ratios):.2f}x).",
        ]
    lines += [
        "",
        "The default since this table: `sfm --finer-below 400` extracts at -1 and, when the median "
        "frame has fewer than 400 keypoints, again at -2 (the keypoints column of a -1 row "
        "that needed a remedy counts the remedy's extraction). So the Himax sequences and the "
        "orbit run at -2 and the textured simulated flights at -1.",
    ]
    return "\n".join(lines) + "\n"


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--work", type=Path, default=Path("/tmp/dronecap-sift-octave"))
    p.add_argument("--octaves", type=int, nargs=2, default=[-1, -2])
    p.add_argument("--only", nargs="*", help="substrings of the case names to run")
    p.add_argument("--frames", type=int, default=240, help="source frames of simulated flights")
    args = p.parse_args()
    args.work.mkdir(parents=True, exist_ok=True)
    rerun_on_snapshot(args.work, Path(__file__))
    load = subprocess.run(["uptime"], capture_output=True, text=True).stdout.strip()
    names = [n for n in CASES if args.only is None or any(s in n for s in args.only)]
    tasks = [(n, o) for n in names for o in args.octaves]
    with ProcessPoolExecutor(max_workers=2) as pool:
        futures = [pool.submit(one, n, o, args.work, args.frames) for n, o in tasks]
        rows = [f.result() for f in futures]
    text = table(rows, args.octaves, load)
    RESULTS.mkdir(parents=True, exist_ok=True)
    (RESULTS / "sift_octave.md").write_text(text)
    sys.stdout.write(text)


if __name__ == "__main__":
    main()
