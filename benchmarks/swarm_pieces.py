"""One capture cut into four overlapping pieces, each zoomed and resized differently: four
"drones" with four cameras. Does the default ``ingest A B C D`` + ``sfm`` put them in one model?

Cases:

- ``lego orbit``: the 200 lego test views on white (``benchmarks/white_orbit.py``'s video), cut
  into 4 pieces of 50 views plus 8 on each side shared with the neighbours; piece k is
  centre-cropped by zoom ``ZOOM[k]`` and resized to ``SIZE[k]`` (so each piece has its own focal
  length after ingest) and written as an mp4v video. Against the Blender poses (a swarm.json
  naming each piece's ground truth): registered per piece, ATE, rotation, and each piece's
  estimated focal length against its true one (``f x zoom``, at 160 px).
- ``himax test_23``: the real HM01B0 street sequence (72 frames) cut into 4 pieces of 24 frames
  (6 shared with each neighbour), zoomed and resized the same way, as PNG folders. No ground
  truth: the reference is the default ``sfm`` of the uncut sequence; ATE / rotation of the
  pieces' model against it after one similarity alignment.

Every piece's camera is estimated (no calibration is given), shared by that piece's frames.
Writes ``benchmarks/results/swarm_pieces.md``. Usage::

    nice .venv/bin/python benchmarks/swarm_pieces.py [--only lego|himax] [--work DIR]

Floor (issue 26): >= 95 % registered in one model, ATE <= 0.5 %.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

import cv2
import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from benchmarks.white_orbit import BLENDER_TO_OPENCV  # noqa: E402
from dronecap.cli import main  # noqa: E402
from dronecap.datasets import open_dataset  # noqa: E402
from dronecap.sfm.align import pose_accuracy  # noqa: E402
from tests.capture.conftest import white_orbit_frames, write_video  # noqa: E402
from tests.conftest import LEGO_DIR, SHARED_DATA  # noqa: E402

ZOOM = (1.0, 1.08, 1.16, 1.25)  # centre crop of 1/zoom of the frame: focal x zoom
SIZE = (160, 224, 128, 200)  # the piece's frames resized to SIZE x SIZE (aspect kept)
HIMAX = SHARED_DATA / "himax_hm01b0" / "test_23"


def pieces(n: int, count: int = 4, shared: int = 8) -> list[range]:
    """``count`` consecutive pieces of ``n`` frames, each sharing ``shared`` with a neighbour."""
    step = n // count
    return [range(max(0, k * step - shared), min(n, (k + 1) * step + shared)) for k in range(count)]


def zoomed(gray: np.ndarray, zoom: float, size: int) -> np.ndarray:
    """The centre 1/zoom of a square-cropped frame, resized to size x size."""
    h, w = gray.shape
    side = int(round(min(h, w) / zoom))
    y, x = (h - side) // 2, (w - side) // 2
    return cv2.resize(gray[y : y + side, x : x + side], (size, size), interpolation=cv2.INTER_AREA)


def lego_case(work: Path) -> tuple[list[Path], Path | None, list[float]]:
    """Four piece videos of the white lego orbit, their swarm.json and true focal lengths."""
    doc = json.loads((LEGO_DIR / "transforms_test.json").read_text())
    views = [int(Path(f["file_path"]).name.split("_")[1]) for f in doc["frames"]]
    c2w = np.array([f["transform_matrix"] for f in doc["frames"]]) @ BLENDER_TO_OPENCV
    frames = white_orbit_frames(LEGO_DIR, views)
    f160 = 0.5 * 160 / np.tan(0.5 * float(doc["camera_angle_x"])) * 160 / frames[0].shape[1]
    sources, drones = [], []
    for k, part in enumerate(pieces(len(frames))):
        video = work / f"piece_{k}.mp4"
        write_video(video, [zoomed(frames[i], ZOOM[k], SIZE[k]) for i in part], fourcc="mp4v")
        gt = work / f"piece_{k}_gt.json"
        truth = [{"index": j, "c2w": c2w[i].tolist()} for j, i in enumerate(part)]
        gt.write_text(json.dumps({"frames": truth}))
        sources.append(video)
        drones.append({"name": video.stem, "ground_truth": gt.name})
    swarm = work / "swarm.json"
    swarm.write_text(json.dumps({"drones": drones}))
    return sources, swarm, [f160 * z for z in ZOOM]


def himax_case(work: Path) -> tuple[list[Path], None, list[float]]:
    """Four piece folders of Himax test_23 (no ground truth, focal lengths unknown)."""
    names = sorted(HIMAX.glob("frame_*.pgm"), key=lambda p: int(p.stem.split("_")[1]))
    frames = [cv2.imread(str(p), cv2.IMREAD_GRAYSCALE) for p in names]
    sources = []
    for k, part in enumerate(pieces(len(frames), shared=6)):
        folder = work / f"piece_{k}"
        folder.mkdir(parents=True, exist_ok=True)
        for j, i in enumerate(part):
            cv2.imwrite(str(folder / f"frame_{j:04d}.png"), zoomed(frames[i], ZOOM[k], SIZE[k]))
        sources.append(folder)
    return sources, None, []


def dronecap(argv: list[str]) -> tuple[int, float]:
    t = time.perf_counter()
    code = main(["-q", *argv])
    return code, time.perf_counter() - t


def run_case(name: str, work: Path) -> dict[str, object]:
    work.mkdir(parents=True, exist_ok=True)
    sources, gt, focal = lego_case(work) if name == "lego orbit" else himax_case(work)
    code, t_ingest = dronecap(["ingest", *map(str, sources), "--workdir", str(work)])
    if code:
        return {"case": name, "error": "ingest failed"}
    sfm = ["sfm", "--workdir", str(work), "--quiet"] + (["--gt", str(gt)] if gt else [])
    code, t_sfm = dronecap(sfm)
    report = json.loads((work / "sfm" / "report.json").read_text())
    row: dict[str, object] = {
        "case": name,
        "registered": f"{report['registered']}/{report['frames_total']}",
        "per piece": " ".join(f"{d['registered']}/{d['frames']}" for d in report.get("drones", [])),
        "linked": all(d["linked"] for d in report.get("drones", [])),
        "ingest s": round(t_ingest, 1),
        "sfm s": round(t_sfm),
    }
    if focal:
        err = [100 * (d["fx"] / f - 1) for d, f in zip(report["drones"], focal, strict=True)]
        row["focal error % per piece"] = " ".join(f"{e:+.2f}" for e in err)
    acc = report.get("accuracy") or (reference_accuracy(work) if code == 0 else {})
    row["ATE %"] = round(acc["ate_percent"], 3) if "ate_percent" in acc else "-"
    row["rotation median deg"] = round(acc["rot_median_deg"], 3) if "rot_median_deg" in acc else "-"
    return row


def reference_accuracy(work: Path) -> dict[str, float]:
    """The pieces' posed.h5 against the default sfm of the uncut Himax sequence."""
    ref = work / "uncut"
    if not (ref / "posed.h5").exists():
        assert dronecap(["ingest", str(HIMAX), "--workdir", str(ref)])[0] == 0
        assert dronecap(["sfm", "--workdir", str(ref), "--quiet"])[0] == 0
    uncut, cut = open_dataset(ref / "posed.h5"), open_dataset(work / "posed.h5")
    truth = {int(s): p for s, p in zip(uncut.source_index, uncut.poses, strict=True)}
    n = len(list(HIMAX.glob("frame_*.pgm")))
    starts = [p[0] for p in pieces(n, shared=6)]  # piece k's frame j is source frame start+j
    source = [starts[d] + int(j) for d, j in zip(cut.drones(), cut.source_index, strict=True)]
    have = [i for i, s in enumerate(source) if s in truth]
    gt = np.stack([truth[source[i]] for i in have])
    return pose_accuracy(cut.poses[have], gt).to_dict()


def main_cli() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--work", type=Path, default=Path("/tmp/dronecap_swarm_pieces"))
    ap.add_argument("--only", choices=("lego", "himax"))
    args = ap.parse_args()
    cases = [c for c in ("lego orbit", "himax test_23") if not args.only or args.only in c]
    rows = [run_case(c, args.work / c.replace(" ", "_")) for c in cases]
    load = subprocess.run(["uptime"], capture_output=True, text=True).stdout.strip()
    cols = list(dict.fromkeys(k for r in rows for k in r))
    table = "| " + " | ".join(cols) + " |\n|" + "---|" * len(cols) + "\n"
    table += "".join("| " + " | ".join(str(r.get(c, "")) for c in cols) + " |\n" for r in rows)
    text = (
        "# One capture cut into four zoomed, resized pieces: four cameras, one model?\n\n"
        f"Command: `nice .venv/bin/python benchmarks/swarm_pieces.py`"
        f"{' --only ' + args.only if args.only else ''}\n\nLoad: `{load}`\n\n"
        f"Zoom per piece {ZOOM}, size {SIZE}; default ingest and sfm (cameras estimated).\n\n"
        f"{table}"
    )
    print(text)
    (REPO / "benchmarks" / "results" / "swarm_pieces.md").write_text(text)


if __name__ == "__main__":
    main_cli()
