"""SfM accuracy and speed: the issue's floors, and speed against error for matcher settings.

Flights (built once in --work, deterministic):

- corridor: ``simulate`` corridor, 300 frames, seed 0 -> ``ingest`` with its default selection
  ("corridor-sel") and with a denser one (``--min-motion 0.5``, "corridor-dense");
- lego: the 200 NeRF Synthetic lego test views (a smooth double orbit, exact poses), gray on
  white, with the true intrinsics ("lego") or without any ("lego-nointr", SIMPLE_RADIAL).

Every run goes through :func:`dronecap.sfm.pipeline.run_sfm` with ground truth, so the numbers
are what ``dronecap sfm --gt`` prints. Writes ``benchmarks/results/sfm_accuracy.md`` and
``sfm_accuracy.png``. Usage::

    nice .venv/bin/python benchmarks/sfm_accuracy.py [--quick] [--repeat 1]
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
from dataclasses import replace
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
RESULTS = REPO / "benchmarks" / "results"
LEGO = REPO.parent / "shared" / "data" / "nerf_synthetic_160" / "lego"

FLOORS = {  # scene -> (registered %, median rotation deg, ATE % of extent, total seconds)
    "corridor-sel": (95.0, 1.0, 2.0, 120.0),
    "corridor-dense": (95.0, 1.0, 2.0, 120.0),
    "lego": (90.0, None, 2.0, None),
    "lego-nointr": (90.0, None, 2.0, None),
}


def build_flights(work: Path) -> dict[str, tuple[Path, Path]]:
    """scene name -> (frames.h5, poses.json), building what is missing."""
    from dronecap.cli import main as cli
    from dronecap.datasets.format import write_dataset
    from dronecap.sfm.blender_flight import blender_flight

    work.mkdir(parents=True, exist_ok=True)
    flights = {}
    video, gt = work / "corridor.mkv", work / "corridor.json"
    if not gt.exists():
        from dronecap.simulator.simulate import simulate

        simulate("corridor", video, frames=300, seed=0, progress=False)
    for name, extra in (("corridor-sel", []), ("corridor-dense", ["--min-motion", "0.5"])):
        frames = work / f"{name}.h5"
        if not frames.exists() and cli(["ingest", str(video), "-o", str(frames), *extra]) != 0:
            sys.exit(f"ingest failed for {name}")
        flights[name] = (frames, gt)
    if LEGO.exists():
        ds, doc = blender_flight(LEGO)
        lego_gt = work / "lego.json"
        lego_gt.write_text(json.dumps(doc))
        for name, known in (("lego", True), ("lego-nointr", False)):
            frames = work / f"{name}.h5"
            if not frames.exists():
                write_dataset(frames, ds if known else replace(ds, intrinsics=None))
            flights[name] = (frames, lego_gt)
    return flights


def settings(quick: bool) -> list[tuple[str, str, dict]]:
    """(scene, label, SfmOptions overrides) of every run, floors first."""
    runs = [(s, "default", {}) for s in FLOORS]
    sweep = [
        ("seq ov5 +loops", {"matcher": "sequential", "overlap": 5}),
        ("seq ov10 +loops", {"matcher": "sequential", "overlap": 10}),
        ("seq ov20 +loops", {"matcher": "sequential", "overlap": 20}),
        ("seq ov10 no loops", {"matcher": "sequential", "loop_detection": False}),
        ("seq ov10 quadratic", {"matcher": "sequential", "quadratic_overlap": True}),
        ("exhaustive", {"matcher": "exhaustive"}),
        ("seq ov10 512 feat", {"matcher": "sequential", "max_features": 512}),
        ("seq ov10 octave 0", {"matcher": "sequential", "first_octave": 0}),
    ]
    sweep = [s for s in sweep if s[0] != "seq ov10 +loops"]  # = the default row (106 frames)
    runs += [("corridor-sel", label, o) for label, o in (sweep[:2] if quick else sweep)]
    keep = ("seq ov10 no loops", "seq ov10 512 feat", "seq ov10 octave 0")
    lego_sweep = [s for s in sweep if s[0] in keep]
    runs += [("lego", label, o) for label, o in ([] if quick else lego_sweep)]
    return runs


def run_one(frames: Path, gt: Path, out: Path, overrides: dict) -> dict:
    """One run_sfm; returns the row of the table (failures become a row too)."""
    from dronecap.errors import InputError
    from dronecap.sfm.options import SfmOptions
    from dronecap.sfm.pipeline import run_sfm

    opts = SfmOptions(min_registration=0.0, **overrides)
    try:
        rep = run_sfm(frames, out / "posed.h5", out / "sfm", opts, gt, progress=False)
    except InputError:
        rep = json.loads((out / "sfm" / "report.json").read_text())
    acc = rep.get("accuracy", {})
    return {
        "frames": rep["frames_total"],
        "reg": 100.0 * rep["registration_rate"],
        "ate": acc.get("ate_percent", float("nan")),
        "rot_med": acc.get("rot_median_deg", float("nan")),
        "rot_max": acc.get("rot_max_deg", float("nan")),
        "reproj": rep.get("quality", {}).get("mean_reprojection_error_px", float("nan")),
        "models": len(rep.get("models", {})),
        "t_match": rep["times"].get("match", 0.0),
        "t_total": rep["times"]["total"],
        "matcher": rep.get("matching", {}).get("matcher", "-"),
    }


def floor_verdict(scene: str, row: dict) -> str:
    """'met' / 'NOT met (...)' against the issue's floors for that scene."""
    reg, rot, ate, secs = FLOORS[scene]
    misses = []
    if row["reg"] < reg:
        misses.append(f"registered {row['reg']:.1f}% < {reg}%")
    if rot is not None and not row["rot_med"] <= rot:
        misses.append(f"rotation {row['rot_med']:.2f} > {rot} deg")
    if not row["ate"] <= ate:
        misses.append(f"ATE {row['ate']:.2f}% > {ate}%")
    if secs is not None and row["t_total"] > secs:
        misses.append(f"time {row['t_total']:.0f} s > {secs} s")
    return "met" if not misses else "NOT met: " + "; ".join(misses)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--work", default="/tmp/dronecap_sfm_bench", help="scratch folder")
    ap.add_argument("--quick", action="store_true", help="floors + two sweep settings only")
    ap.add_argument("--repeat", type=int, default=1, help="runs per setting (median time)")
    args = ap.parse_args()
    work = Path(args.work)
    flights = build_flights(work)
    rows = []
    for scene, label, overrides in settings(args.quick):
        if scene not in flights:
            print(f"skip {scene}: data not found")
            continue
        frames, gt = flights[scene]
        reps = [
            run_one(frames, gt, work / "runs" / f"{scene}-{label}".replace(" ", "_"), overrides)
            for _ in range(args.repeat)
        ]
        row = dict(reps[0], scene=scene, label=label)
        row["t_total"] = statistics.median(r["t_total"] for r in reps)
        row["t_match"] = statistics.median(r["t_match"] for r in reps)
        rows.append(row)
        print(
            f"{scene:15s} {label:20s} reg {row['reg']:5.1f}%  ATE {row['ate']:6.3f}%  rot med "
            f"{row['rot_med']:5.2f} max {row['rot_max']:5.2f} deg  {row['t_total']:5.1f} s",
            flush=True,
        )
    write_results(rows, args.repeat)


def write_results(rows: list[dict], repeat: int) -> None:
    """Markdown table + PNG plot of time against ATE."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    head = (
        "| scene | setting | matcher | frames | registered % | ATE % extent | rot median deg | "
        "rot max deg | reproj px | models | match s | total s | floors |\n"
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|\n"
    )
    lines = []
    for r in rows:
        verdict = floor_verdict(r["scene"], r) if r["label"] == "default" else ""
        lines.append(
            f"| {r['scene']} | {r['label']} | {r['matcher']} | {r['frames']} | {r['reg']:.1f} | "
            f"{r['ate']:.3f} | {r['rot_med']:.2f} | {r['rot_max']:.2f} | {r['reproj']:.3f} | "
            f"{r['models']} | {r['t_match']:.1f} | {r['t_total']:.1f} | {verdict} |"
        )
    text = (
        "# SfM accuracy and speed (`nice .venv/bin/python benchmarks/sfm_accuracy.py`)\n\n"
        "2-core shared machine; times are medians of "
        f"{repeat} run(s) and noisy (other jobs ran at the same time). ATE is the RMSE of camera "
        "centres after a Umeyama similarity alignment, as % of the ground-truth trajectory's "
        "bounding-box diagonal; rotation errors are after the same alignment.\n\n"
        + head
        + "\n".join(lines)
        + "\n"
    )
    RESULTS.mkdir(parents=True, exist_ok=True)
    (RESULTS / "sfm_accuracy.md").write_text(text)
    print(text)
    fig, ax = plt.subplots(figsize=(8, 5))
    for scene in dict.fromkeys(r["scene"] for r in rows):
        pts = [r for r in rows if r["scene"] == scene]
        ax.scatter([r["t_total"] for r in pts], [r["ate"] for r in pts], label=scene)
        for r in pts:
            ax.annotate(r["label"], (r["t_total"], r["ate"]), fontsize=7)
    ax.set_xlabel("total sfm time (s)")
    ax.set_ylabel("ATE (% of trajectory extent)")
    ax.set_title("dronecap sfm: speed against error per matcher setting")
    ax.legend()
    fig.tight_layout()
    fig.savefig(RESULTS / "sfm_accuracy.png", dpi=110)


if __name__ == "__main__":
    main()
