"""A swarm posed together: N simulated drones of one scene -> ingest -> sfm -> one model?

For N in --drones (default 2 4): ``dronecap simulate --drones N --sensor S --frames F`` (each
drone its own camera and onboard drift), default ``dronecap ingest`` of the swarm folder and
default ``dronecap sfm``; then, against the simulator's ground truth (one world frame for every
drone): frames registered per drone (in the one posed.h5), ATE (% of the scene extent) and
median rotation error after one similarity alignment of all drones together, each drone's
focal-length error (the posed file's camera of that drone, against the drone's true focal
length scaled to the stored size), and the wall time of each stage. Writes
``benchmarks/results/swarm.md`` and ``swarm.png`` (top view of the aligned trajectories, one
colour per drone). A stage that fails is recorded with its one-line message. Usage::

    nice .venv/bin/python benchmarks/swarm.py [--drones 2 4 8] [--frames 300] [--sensor aideck]
"""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
RESULTS = REPO / "benchmarks" / "results"


def stage(argv: list[str]) -> tuple[float, str]:
    """Run one dronecap command; (seconds, "" or its error line)."""
    from dronecap.cli import main

    err = io.StringIO()
    t0 = time.perf_counter()
    with contextlib.redirect_stderr(err):
        try:
            code = main(["-q", *argv])
        except SystemExit as stop:  # argparse's usage errors
            code = stop.code if isinstance(stop.code, int) else 2
    lines = [x for x in err.getvalue().splitlines() if "warning" not in x]
    return time.perf_counter() - t0, "" if code == 0 else (lines[-1] if lines else f"exit {code}")


def measure(swarm: Path, posed: Path) -> dict[str, object]:
    """Registration, ATE, rotation and focal errors of ``posed`` against the swarm's truth."""
    from dronecap.datasets import open_dataset
    from dronecap.sfm.align import pose_accuracy, umeyama

    doc = json.loads((swarm / "swarm.json").read_text())
    truth = [json.loads((swarm / d["ground_truth"]).read_text()) for d in doc["drones"]]
    ds = open_dataset(posed)
    drones = ds.drones()
    gt = np.stack(
        [
            np.array(truth[d]["frames"][int(i)]["c2w"])
            for d, i in zip(drones, ds.source_index, strict=True)
        ]
    )
    acc = pose_accuracy(ds.poses, gt)
    sim = umeyama(ds.poses[:, :3, 3], gt[:, :3, 3])
    aligned = sim.apply_poses(ds.poses)[:, :3, 3]
    per = []
    for d, t in enumerate(truth):
        mine = np.flatnonzero(drones == d)
        k = ds.camera_of(int(mine[0])) if len(mine) else None
        true_fx = t["intrinsics"]["fx"] * (k.width / t["intrinsics"]["width"]) if k else None
        per.append(
            {
                "drone": ds.drone_name(d),
                "registered": int(len(mine)),
                "focal_err_pct": None if k is None else 100 * abs(k.fx / true_fx - 1),
            }
        )
    tracks = [(aligned[drones == d, :2].tolist(), gt[drones == d, :2, 3].tolist())
              for d in range(len(truth))]  # fmt: skip
    return {
        "ate_pct": acc.ate_percent,
        "rot_med_deg": acc.rot_median_deg,
        "per_drone": per,
        "tracks": tracks,
    }


def run_one(n: int, frames: int, sensor: str, work: Path) -> dict[str, object]:
    """Simulate, ingest and pose one swarm of ``n`` drones; its row of the table."""
    root = work / f"n{n}"
    swarm, fh5, sfm_dir = root / "swarm", root / "frames.h5", root / "sfm"
    row: dict[str, object] = {"drones": n, "frames": frames, "sensor": sensor}
    steps = {
        "simulate": ["simulate", "--drones", str(n), "--frames", str(frames), "--sensor", sensor,
                     "-o", str(swarm)],
        "ingest": ["ingest", str(swarm), "-o", str(fh5)],
        "sfm": ["sfm", "--frames", str(fh5), "--workdir", str(sfm_dir)],
    }  # fmt: skip
    for name, argv in steps.items():
        if name == "simulate" and (swarm / "swarm.json").exists():
            continue
        seconds, error = stage(argv)
        row[f"{name}_s"] = round(seconds, 1)
        if error:
            row["error"] = f"{name}: {error}"
            return row
    from dronecap.datasets import open_dataset

    row["kept"] = open_dataset(fh5).n
    row.update(measure(swarm, sfm_dir / "posed.h5"))
    return row


def write(rows: list[dict[str, object]], load: str) -> None:
    """The markdown table."""
    lines = [
        "# Swarm: N simulated drones posed in one model (`benchmarks/swarm.py`)",
        "",
        f"Load average at start: {load}. Per drone: registered frames / focal error.",
        "",
        "| drones | frames/drone | sensor | kept | registered | ATE % | rot. median ° | "
        "focal err % (max) | simulate s | ingest s | sfm s | note |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        per = r.get("per_drone", [])
        reg = " / ".join(str(p["registered"]) for p in per) or "-"
        focal = [p["focal_err_pct"] for p in per if p["focal_err_pct"] is not None]
        cells = [
            r["drones"], r["frames"], r["sensor"], r.get("kept", "-"), reg,
            f"{r['ate_pct']:.2f}" if "ate_pct" in r else "-",
            f"{r['rot_med_deg']:.2f}" if "rot_med_deg" in r else "-",
            f"{max(focal):.2f}" if focal else "-",
            r.get("simulate_s", "cached"), r.get("ingest_s", "-"), r.get("sfm_s", "-"),
            r.get("error", ""),
        ]  # fmt: skip
        lines.append("| " + " | ".join(str(c) for c in cells) + " |")
    RESULTS.mkdir(parents=True, exist_ok=True)
    (RESULTS / "swarm.md").write_text("\n".join(lines) + "\n")
    plot(rows)


def plot(rows: list[dict[str, object]]) -> None:
    """Top view of every measured swarm: truth (thin) and aligned estimate (dots) per drone."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    done = [r for r in rows if "tracks" in r]
    if not done:
        return
    fig, axes = plt.subplots(1, len(done), figsize=(5 * len(done), 4), squeeze=False)
    for ax, r in zip(axes[0], done, strict=True):
        for d, (est, true) in enumerate(r["tracks"]):  # type: ignore[arg-type]
            colour = f"C{d}"
            t, e = np.array(true).reshape(-1, 2), np.array(est).reshape(-1, 2)
            ax.plot(t[:, 0], t[:, 1], "-", color=colour, lw=0.8, label=f"drone {d} truth")
            ax.plot(e[:, 0], e[:, 1], ".", color=colour, ms=3)
        ax.set_title(f"{r['drones']} drones, ATE {r['ate_pct']:.2f} %")
        ax.set_aspect("equal")
        ax.set_xlabel("x (m)")
        ax.set_ylabel("y (m)")
    axes[0][0].legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(RESULTS / "swarm.png", dpi=110)


def main(argv: list[str] | None = None) -> int:
    """Run every swarm size and write the results."""
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--drones", type=int, nargs="+", default=[2, 4])
    p.add_argument("--frames", type=int, default=300)
    p.add_argument("--sensor", default="aideck")
    p.add_argument("--work", type=Path, default=REPO / "benchmarks" / ".work" / "swarm")
    a = p.parse_args(argv)
    load = Path("/proc/loadavg").read_text().split()[:3]
    rows = [run_one(n, a.frames, a.sensor, a.work) for n in a.drones]
    write(rows, " ".join(load))
    print((RESULTS / "swarm.md").read_text())
    return 0


if __name__ == "__main__":
    sys.exit(main())
