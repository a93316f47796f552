"""The README's main pipeline, end to end with tiny settings: a simulated corridor flight through
ingest, real COLMAP, split, shard and a short training run; then a re-run that is all cache hits."""

from __future__ import annotations

import json
import math
from pathlib import Path

from dronecap import cli
from dronecap.pipeline import read_stamp

TINY = ["frames=90", "steps=30", "train.preset=test"]


def test_demo_pipeline_tiny(tmp_path: Path, capsys) -> None:
    assert cli.main(["run", "demo", *TINY, "--workdir", str(tmp_path)]) == 0
    runs = tmp_path / "runs" / "demo"
    report = json.loads((runs / "sfm" / "report.json").read_text())
    assert report["registration_rate"] >= 0.8
    assert report["accuracy"]["ate_percent"] < 5.0  # against the simulator's ground truth
    metrics = json.loads((runs / "train" / "metrics.json").read_text())
    assert math.isfinite(metrics["test"]["psnr"]) and metrics["test"]["views"] > 0
    assert len(list((runs / "shard" / "shards").glob("client_*.h5"))) == 4
    text = (runs / "report.md").read_text()
    assert "| sfm | ran |" in text and "PSNR" in text and "GAP9" in text
    out = capsys.readouterr().out
    assert "registered" in out and "report:" in out
    # The pictures: kept frames, trajectory against the ground truth, training curve, labelled
    # truth | render | error, fly-through; all embedded in one self-contained report.html.
    pics = {p.name for p in (runs / "pictures").iterdir()}
    assert {"ingest_kept_frames.png", "sfm_trajectory.png", "train_curve.png"} <= pics
    assert {"train_truth_render_error.png", "train_flythrough.webp"} <= pics
    page = (runs / "report.html").read_text()
    assert page.count("data:image/png;base64,") >= 4 and "data:image/webp;base64," in page
    assert "work/images" not in text  # the SfM picture is the trajectory, not raw input frames

    # Nothing changed: the second run is all cache hits and rewrites no stamp.
    stamps = {p.parent.name: p.stat().st_mtime_ns for p in runs.glob("*/.dronecap-stage.json")}
    assert cli.main(["run", "demo", *TINY, "--workdir", str(tmp_path)]) == 0
    assert {
        p.parent.name: p.stat().st_mtime_ns for p in runs.glob("*/.dronecap-stage.json")
    } == stamps
    assert all(read_stamp(runs / s)["status"] == "done" for s in stamps)
