"""A time-budgeted training run with this code against an earlier commit's, in turn.

The issue's command, ``dronecap train DATASET --time-budget B --threads 1``, on lego (imported
from the Blender files), the simulated corridor and real Himax test_23 (both built by
``scene_sized.build_scene``), with ``git archive`` snapshots of ``--current`` (HEAD: edits
in progress stay out) and of ``--previous``, alternating: test PSNR over all test views, steps
trained and the median step. A change that makes steps faster without changing their
arithmetic shows here as more steps and more dB in the same seconds (``time_to_quality.py
compare`` compares settings of one code in one process instead). Runs are kept under
``--cache`` and reused when they finished, so an interrupted comparison resumes.

    PYTHONPATH=. .venv/bin/python benchmarks/budget_code_compare.py --previous 3276441 \\
        --budgets 10 60 --rounds 2 1 --out time_to_quality_code_s23
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
from pathlib import Path

import _runs as shared
from scene_sized import build_scene
from snapshot import RESULTS, unpack

SCENES = ("lego", "corridor", "himax-test_23")


def dataset_of(scene: str, cache: Path) -> Path:
    """The dataset file of ``scene`` (built or imported into ``cache`` once)."""
    if scene == "lego":
        shared.open_scene("lego", cache)
        return cache / "lego.h5"
    return build_scene(scene, cache)


def train(code: Path, dataset: Path, budget: float, run: Path) -> dict:
    """``dronecap train`` of the tree ``code`` into ``run`` (reused when it has metrics.json);
    {psnr, steps, ms, views, load, code}."""
    metrics = run / "metrics.json"
    if not metrics.exists():
        cmd = [sys.executable, "-m", "dronecap.cli", "train", str(dataset), "--time-budget",
               str(budget), "--threads", "1", "--out", str(run), "--no-progress"]  # fmt: skip
        env = dict(os.environ, PYTHONPATH=str(code), OMP_NUM_THREADS="1")
        # outside the repository: `python -m` puts its working directory first on sys.path
        p = subprocess.run(cmd, env=env, cwd=run.parent, capture_output=True, text=True)
        if p.returncode != 0:
            raise SystemExit(f"{run.name} failed: {p.stderr.strip()[-400:]}")
    m = json.loads(metrics.read_text())
    return {"psnr": m["test"]["psnr"], "steps": m["steps"], "ms": m["ms_per_step_median"],
            "views": m["test"]["views"], "load": os.getloadavg()[0]}  # fmt: skip


def table(rows: list[dict], previous: str, current: str) -> list[str]:
    """The results page: one line per run pair, then the medians per scene and budget."""
    lines = [
        "| scene | budget (s) | round | previous code: dB (steps, ms/step) | this code | load |",
        "|---|---:|---:|---:|---:|---:|",
    ]
    for r in rows:
        o, n = r["old"], r["new"]
        lines.append(
            f"| {r['scene']} | {r['budget']:g} | {r['round']} | {o['psnr']:.2f} ({o['steps']}, "
            f"{o['ms']:.1f}) | **{n['psnr']:.2f}** ({n['steps']}, {n['ms']:.1f}) | "
            f"{n['load']:.1f} |"
        )
    lines += ["", "Medians over rounds:", "", "| scene | budget (s) | previous | this | gain |",
              "|---|---:|---:|---:|---:|"]  # fmt: skip
    for key in dict.fromkeys((r["scene"], r["budget"]) for r in rows):
        old = statistics.median(r["old"]["psnr"] for r in rows if (r["scene"], r["budget"]) == key)
        new = statistics.median(r["new"]["psnr"] for r in rows if (r["scene"], r["budget"]) == key)
        lines.append(f"| {key[0]} | {key[1]:g} | {old:.2f} | {new:.2f} | {new - old:+.2f} |")
    return [
        "# Time-budgeted training: this code against an earlier commit",
        "",
        f"`dronecap train DATASET --time-budget B --threads 1`, this code = `{current}`, "
        f"previous code = `{previous}`, "
        "the two in turn, one run at a time (load = 1-minute load average after the run; 1.0 is "
        "the run itself). PSNR over all test views of the dataset.",
        "",
        *lines,
    ]


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--previous", required=True, help="earlier commit to compare with")
    p.add_argument("--current", default="HEAD", help="the commit measured as this code")
    p.add_argument("--scenes", default=",".join(SCENES))
    p.add_argument("--budgets", type=float, nargs="+", default=[10.0, 60.0])
    p.add_argument("--rounds", type=int, nargs="+", default=[2, 1], help="per budget")
    p.add_argument("--cache", default="/tmp/dronecap-time-to-quality")
    p.add_argument("--out", default="time_to_quality_code")
    args = p.parse_args()
    cache = Path(args.cache)
    old, new = unpack(args.previous, cache), unpack(args.current, cache)
    work = cache / f"code-compare-{args.out}"
    rows = []
    for budget, rounds in zip(args.budgets, args.rounds, strict=True):
        for rnd in range(1, rounds + 1):
            for scene in args.scenes.split(","):
                data = dataset_of(scene, cache)
                runs = {}
                for tag, code in (("old", old), ("new", new)):
                    run = work / f"{scene}-{budget:g}-{tag}-{rnd}"
                    run.parent.mkdir(parents=True, exist_ok=True)
                    runs[tag] = train(code, data, budget, run)
                rows.append({"scene": scene, "budget": budget, "round": rnd, **runs})
                print(f"{scene} {budget:g} s round {rnd}: {runs['old']['psnr']:.2f} -> "
                      f"{runs['new']['psnr']:.2f} dB", flush=True)  # fmt: skip
    current = new.name.removeprefix("snapshot-")
    shared.write_page(table(rows, args.previous, current), RESULTS / f"{args.out}.md")


if __name__ == "__main__":
    main()
