"""White-background orbit (issue 15 floor): the 200 lego test views on pure white, as a video.

Builds ``orbit.mp4`` (mp4v) from ``nerf_synthetic_160/lego/test`` composited on 255 white and
converted to gray, plus ``orbit_gt.json`` (the test poses in OpenCV camera axes, indexed by video
frame) and runs the DEFAULT commands ``dronecap ingest orbit.mp4`` and ``dronecap sfm --gt
orbit_gt.json`` (with ``--threads 1``). Prints and writes ``benchmarks/results/white_orbit.md``:
frames kept, spacing of the kept views (degrees), registered %, ATE, rotation error.

    OMP_NUM_THREADS=1 nice .venv/bin/python benchmarks/white_orbit.py [--out DIR] [ingest flags]

Floors: >= 95 % of the kept frames registered, ATE <= 0.5 %, rotation median <= 1 degree.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from dronecap.cli import main  # noqa: E402
from dronecap.datasets import open_dataset  # noqa: E402
from tests.capture.conftest import white_orbit_frames, write_video  # noqa: E402
from tests.conftest import LEGO_DIR  # noqa: E402

BLENDER_TO_OPENCV = np.diag([1.0, -1.0, -1.0, 1.0])  # camera axes: y up, z back -> y down, z fwd


def build(out: Path) -> tuple[Path, Path, np.ndarray]:
    """orbit.mp4, orbit_gt.json and the OpenCV c2w [200, 4, 4] of the frames."""
    doc = json.loads((LEGO_DIR / "transforms_test.json").read_text())
    views = [int(Path(f["file_path"]).name.split("_")[1]) for f in doc["frames"]]
    c2w = np.array([f["transform_matrix"] for f in doc["frames"]]) @ BLENDER_TO_OPENCV
    video = write_video(out / "orbit.mp4", white_orbit_frames(LEGO_DIR, views), fourcc="mp4v")
    gt = out / "orbit_gt.json"
    frames = [{"index": i, "c2w": m.tolist()} for i, m in enumerate(c2w)]
    gt.write_text(json.dumps({"frames": frames}))
    return video, gt, c2w


def spacing_deg(c2w: np.ndarray, kept: np.ndarray) -> np.ndarray:
    """Angle (degrees) between the viewing directions of consecutive kept frames."""
    z = c2w[kept, :3, 2]
    return np.degrees(np.arccos(np.clip((z[1:] * z[:-1]).sum(1), -1.0, 1.0)))


def run(out: Path, ingest_flags: list[str]) -> dict[str, object]:
    out.mkdir(parents=True, exist_ok=True)
    video, gt, c2w = build(out)
    t0 = time.perf_counter()
    assert main(["-q", "ingest", str(video), "--workdir", str(out), *ingest_flags]) == 0
    t_ingest = time.perf_counter() - t0
    frames = open_dataset(out / "frames.h5")
    gaps = spacing_deg(c2w, np.asarray(frames.source_index))
    t0 = time.perf_counter()
    rc = main(["-q", "sfm", "--workdir", str(out), "--gt", str(gt), "--threads", "1"])
    t_sfm = time.perf_counter() - t0
    report = json.loads((out / "sfm" / "report.json").read_text()) if rc == 0 else {}
    acc = report.get("accuracy", {})
    return {
        "ingest flags": " ".join(ingest_flags) or "(defaults)",
        "kept": f"{frames.n}/200",
        "spacing median/max (deg)": f"{np.median(gaps):.1f} / {gaps.max():.1f}",
        "registered": f"{report['registered']}/{frames.n}" if report else "failed",
        "ATE %": f"{acc['ate_percent']:.3f}" if "ate_percent" in acc else "-",
        "rotation median/max (deg)": (
            f"{acc['rot_median_deg']:.2f} / {acc['rot_max_deg']:.2f}" if acc else "-"
        ),
        "ingest s": f"{t_ingest:.1f}",
        "sfm s": f"{t_sfm:.0f}",
        "accuracy": acc,
    }


def main_cli() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="/tmp/white_orbit", help="work folder")
    ap.add_argument("--results", default=str(REPO / "benchmarks/results/white_orbit.md"))
    args, flags = ap.parse_known_args()
    row = run(Path(args.out), flags)
    load = subprocess.run(["uptime"], capture_output=True, text=True).stdout.strip()
    cols = [k for k in row if k != "accuracy"]
    table = "| " + " | ".join(cols) + " |\n|" + "---|" * len(cols) + "\n"
    table += "| " + " | ".join(str(row[c]) for c in cols) + " |\n"
    text = (
        "# White-background lego orbit: default ingest -> sfm\n\n"
        f"Command: `OMP_NUM_THREADS=1 nice .venv/bin/python benchmarks/white_orbit.py "
        f"{' '.join(flags)}`\n\nLoad: `{load}`\n\n{table}\n"
        f"Full accuracy record: `{json.dumps(row['accuracy'])}`\n"
    )
    print(text)
    Path(args.results).write_text(text)


if __name__ == "__main__":
    main_cli()
