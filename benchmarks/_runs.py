"""What the benchmarks share. The training benchmarks (train_accuracy.py, time_to_quality.py):
their command line, the lego scene, one JSON file per run, the final record of a trained model,
GAP9 memory and the table of runs that stopped early. Every benchmark: printing and writing its
results page, a median wall time, the pixel maps that show an image through a lens."""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import statistics
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

REPO = Path(__file__).resolve().parents[1]
RESULTS = REPO / "benchmarks" / "results"
LEGO = REPO.parent / "shared" / "data" / "nerf_synthetic_160" / "lego"
RENDER_VIEWS = 5  # test views rendered to time a render


def command_line(doc: str) -> tuple[argparse.ArgumentParser, argparse.ArgumentParser]:
    """The parser of a training benchmark (``run NAME`` or ``report``) and its ``run``
    sub-parser, with the options every training benchmark has; the caller adds its own."""
    p = argparse.ArgumentParser(description=doc.split("\n")[0])
    sub = p.add_subparsers(dest="cmd", required=True)
    r = sub.add_parser("run")
    r.add_argument("name")
    r.add_argument("--set", action="append", default=[], metavar="FIELD=VALUE")
    r.add_argument("--seed", type=int, default=0)
    r.add_argument("--threads", type=int, default=1)
    r.add_argument("--curve-every-view", type=int, default=10)
    r.add_argument("--cache", default="/tmp/dronecap_bench")
    sub.add_parser("report")
    return p, r


def open_scene(scene: str, cache: Path):
    """The dataset of ``scene``: "lego", "lego-gray" (imported once into ``cache``) or a path."""
    from dronecap.datasets.blender import import_blender
    from dronecap.datasets.format import open_dataset

    if scene in ("lego", "lego-gray"):
        gray = scene == "lego-gray"
        path = cache / ("lego_gray.h5" if gray else "lego.h5")
        if not path.exists():
            cache.mkdir(parents=True, exist_ok=True)
            import_blender(LEGO, path, color="gray" if gray else "rgb", progress=False)
        return open_dataset(path)
    return open_dataset(Path(scene))


def write_run(runs: Path, obj: dict[str, Any]) -> None:
    """Write one run's JSON ``runs/NAME.json`` (NAME: ``obj["name"]``) whole (partial while
    training, complete at the end): a report reading it meanwhile sees the old or the new."""
    from dronecap.files import atomic_output

    runs.mkdir(parents=True, exist_ok=True)
    with atomic_output(runs / f"{obj['name']}.json") as tmp:
        tmp.write_text(json.dumps(obj, indent=1, default=list) + "\n")


def read_runs(runs: Path) -> list[dict[str, Any]]:
    """Every run's JSON in ``runs``, by name."""
    return [json.loads(p.read_text()) for p in sorted(runs.glob("*.json"))]


def final_record(
    args: argparse.Namespace, tr, ds, curve_views: np.ndarray, ms: list[float], t_start: float
) -> tuple[dict[str, Any], float]:
    """What every run's JSON holds about the trained model ``tr`` (a Trainer) and the run
    ``args``: its evaluation on ALL test views (mean PSNR [dB], SSIM, per view), steps, the
    median of the step times ``ms`` [ms], the render time [s per view] of the first
    :data:`RENDER_VIEWS` test views, size, threads, load and resolved configuration; and the
    mean PSNR [dB] over ``curve_views`` alone (the curve's last point)."""
    full = tr.evaluate(ds)
    on_curve = {int(i) for i in curve_views}
    curve_psnr = float(np.mean([v["psnr"] for v in full["per_view"] if v["index"] in on_curve]))
    t0 = time.perf_counter()
    for i in np.flatnonzero(ds.split == 2)[:RENDER_VIEWS]:
        tr.render(ds.poses[i], ds.intrinsics)
    record = {
        "name": args.name,
        "preset": args.preset,
        "overrides": args.set,
        "seed": args.seed,
        "steps": tr.step,
        "psnr": full["psnr"],
        "ssim": full["ssim"],
        "views": full["views"],
        "per_view_psnr": [v["psnr"] for v in full["per_view"]],
        "render_seconds": (time.perf_counter() - t0) / RENDER_VIEWS,
        "train_seconds": tr.train_seconds,
        "wall_seconds": time.time() - t_start,
        "ms_per_step_median": float(np.median(ms)),
        "parameters": tr.parameter_count(),
        "n_max": tr.cfg.n_max,
        "threads": args.threads,
        "load_average": os.getloadavg()[0],
        "config": dataclasses.asdict(tr.cfg),  # resolved: n_max as trained
    }
    return record, curve_psnr


def memory_mb(cfg_dict: dict[str, Any]) -> float:
    """Modelled GAP9 memory (MB, the paper's Table II accounting: parameters, gradients, Adam
    state, activations, occupancy grid, image) of a run's configuration (gap9/model.py)."""
    from dronecap.gap9.model import cost_report
    from dronecap.nerf.config import config_from_dict

    return cost_report(config_from_dict(cfg_dict))["memory"]["untiled"]["total"] / 1e6


def stopped_table(runs: list[dict[str, Any]], intro: str, seconds: str) -> list[str]:
    """Markdown lines (a blank line, ``intro``, the table) of runs that stopped before their
    final evaluation, at their last curve point; ``seconds`` heads the time column. No lines
    when there are none."""
    if not runs:
        return []
    head = f"| run | step | {seconds} | PSNR dB (20 views) |"
    lines = ["", intro, "", head, "|---|---:|---:|---:|"]
    for r in runs:
        c = r["curve"][-1]
        lines.append(f"| {r['name']} | {c['step']} | {c['seconds']:.0f} | {c['psnr']:.2f} |")
    return lines


def write_page(lines: list[str], path: Path) -> str:
    """Print a results page (its markdown ``lines``) and write it to ``path`` (whole or not at
    all: a temporary beside it, renamed); the text."""
    from dronecap.files import atomic_output

    text = "\n".join(lines) + "\n"
    print(text)
    with atomic_output(path) as tmp:
        tmp.write_text(text)
    return text


def median_seconds(fn: Callable[[], object], repeat: int) -> float:
    """Median wall time of ``fn()`` over ``repeat`` calls, in seconds."""
    times = []
    for _ in range(repeat):
        t = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t)
    return statistics.median(times)


def lens_maps(pinhole: Any, distortion: tuple[float, ...]) -> tuple[np.ndarray, np.ndarray]:
    """``cv2.remap`` maps (x, y), float32 [H, W], that turn an image of camera ``pinhole`` into
    what the same camera with OpenCV lens ``distortion`` sees."""
    lens = dataclasses.replace(pinhole, model="OPENCV", distortion=distortion)
    v, u = np.mgrid[0 : pinhole.height, 0 : pinhole.width]
    xy = lens.undistort_points(np.stack([u.ravel() + 0.5, v.ravel() + 0.5], 1))
    shape = (pinhole.height, pinhole.width)
    map_x = (pinhole.fx * xy[:, 0] + pinhole.cx - 0.5).reshape(shape).astype(np.float32)
    map_y = (pinhole.fy * xy[:, 1] + pinhole.cy - 0.5).reshape(shape).astype(np.float32)
    return map_x, map_y
