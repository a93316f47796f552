"""``kill -9`` at several points of ``ingest``, ``sfm`` and ``dronecap run``: no partial output
under a final name, no orphaned COLMAP process, and a rerun of the same command finishes with
the result of an uninterrupted run and the same files (no temporaries left behind).

The kill points of ``ingest`` and ``sfm`` are parts (:data:`KILL_FRACTIONS`) of the measured
uninterrupted run, so they fall inside the work on a loaded machine too; those of ``run`` are
seconds after a stage starts (:data:`STAGE_KILLS`), as the share of each stage in the run's time
depends on the load (training's evaluation and pictures take most of it on a busy machine).
Every stage here is deterministic: ingest by
construction, SfM with one COLMAP thread (``--threads 1``; with more, COLMAP's parallel
matching and bundle adjustment order their sums differently), training with one torch thread
from a checkpoint. So the results are compared exactly: every array and attribute of the files,
less their clock readings (``created``, ``run_fps``) and input hashes; the trained weights bit
for bit.
Slow: real processes, real work (a simulated flight, a video written with OpenCV).
"""

from __future__ import annotations

import json
import os
import signal
import time
from pathlib import Path

import cv2
import numpy as np
import pytest

from dronecap.datasets.format import open_dataset
from dronecap.pipeline import STAMP
from tests.reliability.conftest import KILL_FRACTIONS, complete, dronecap, kill_at, strays

pytestmark = pytest.mark.slow
FLIGHT_FRAMES = 45  # a short simulated corridor flight: SfM takes ~15 s on one thread
# (stage, seconds after it starts) of each kill -9 of `dronecap run`: a kill in ingest, two in
# SfM (in feature extraction, in matching or mapping), two in training (after 1 s, after 4 s)
STAGE_KILLS = (("ingest", 0.2), ("sfm", 2.0), ("sfm", 10.0), ("train", 1.0), ("train", 4.0))


@pytest.fixture(scope="module")
def flight(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A folder with the simulator's flight.mp4 and flight.json (45 frames, 160x160)."""
    root = tmp_path_factory.mktemp("flight")
    complete(["simulate", "--frames", str(FLIGHT_FRAMES), "--seed", "0"], root)
    return root


@pytest.fixture(scope="module")
def panning_video(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """400 frames of 640x480 panning across a smoothed random texture (mp4v): a few seconds of
    decoding, scoring and tracking for ingest."""
    rng = np.random.default_rng(3)
    texture = cv2.GaussianBlur(rng.integers(0, 256, (480, 1920), dtype=np.uint8), (0, 0), 2.0)
    path = tmp_path_factory.mktemp("video") / "pan.mp4"
    out = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"mp4v"), 30.0, (640, 480))
    for i in range(400):
        out.write(cv2.cvtColor(texture[:, 2 * i : 2 * i + 640], cv2.COLOR_GRAY2BGR))
    out.release()
    return path


def same_data(a: Path, b: Path) -> None:
    """The two dataset files hold the same data: every field, less the clock readings (when the
    file and the files it was made from were made, ingest's decoding speed) and the hashes of
    input files (their bytes hold their own creation time)."""
    x, y = open_dataset(a), open_dataset(b)
    for ds in (x, y):
        prov = ds.provenance
        while prov:  # the file's provenance, then its parent's (split keeps sfm's), ...
            prov.pop("created")
            prov.pop("inputs")
            prov = prov.get("parent")
        ds.attrs.pop("run_fps", None)
    assert x.same_as(y), f"{b} differs from the uninterrupted {a}"


def files_of(root: Path) -> set[str]:
    """Relative names of every file under ``root``."""
    return {str(p.relative_to(root)) for p in root.rglob("*") if p.is_file()}


def colmap_children(cwd: Path) -> list[int]:
    """Pids of COLMAP child processes (``dronecap.sfm.isolate``) working in ``cwd``."""
    found = []
    for proc in Path("/proc").iterdir():
        try:
            cmd = (proc / "cmdline").read_bytes()
            here = os.readlink(proc / "cwd")
        except OSError:  # not a process, or gone meanwhile
            continue
        if b"dronecap.sfm.isolate" in cmd and Path(here) == cwd:
            found.append(int(proc.name))
    return found


def no_colmap_left(cwd: Path, wait_s: float = 10.0) -> None:
    """The COLMAP child of a killed ``dronecap`` ends on its own (it watches its parent)."""
    deadline = time.monotonic() + wait_s
    while colmap_children(cwd) and time.monotonic() < deadline:
        time.sleep(0.2)
    assert not colmap_children(cwd), "a COLMAP child outlived its killed dronecap"


def test_ingest_killed_anywhere_then_rerun(panning_video: Path, tmp_path: Path) -> None:
    ref, work = tmp_path / "ref", tmp_path / "work"
    ref.mkdir(), work.mkdir()
    argv = ["ingest", str(panning_video), "--intrinsics", "none"]
    took = complete(argv, ref)
    cut = 0
    for part in KILL_FRACTIONS:
        kill_at(argv, work, part * took)
        if (work / "frames.h5").exists():  # written before the kill: then whole and the same
            same_data(ref / "frames.h5", work / "frames.h5")
        cut += not (work / "frames.h5").exists()
    assert cut, "every kill came after the work"
    complete(argv, work)
    same_data(ref / "frames.h5", work / "frames.h5")
    assert files_of(work) == files_of(ref)
    assert not strays(work)


def test_sfm_killed_anywhere_then_rerun(flight: Path, tmp_path: Path) -> None:
    ref, work = tmp_path / "ref", tmp_path / "work"
    ref.mkdir(), work.mkdir()
    complete(["ingest", str(flight / "flight.mp4"), "-o", "frames.h5"], ref)
    frames = ref / "frames.h5"
    argv = ["sfm", "--frames", str(frames), "--threads", "1", "--gt", str(flight / "flight.json")]
    took = complete(argv, ref)
    cut = 0
    for part in KILL_FRACTIONS:
        kill_at(argv, work, part * took)
        no_colmap_left(work)
        if (work / "posed.h5").exists():  # the last write: then whole and the same
            same_data(ref / "posed.h5", work / "posed.h5")
        if (work / "sfm" / "report.json").exists():
            json.loads((work / "sfm" / "report.json").read_text())
        cut += (work / "sfm" / "work" / "database.db").exists() and not (work / "posed.h5").exists()
    assert cut, "no kill fell inside COLMAP's work"
    complete(argv, work)
    same_data(ref / "posed.h5", work / "posed.h5")
    a = json.loads((ref / "sfm" / "report.json").read_text())
    b = json.loads((work / "sfm" / "report.json").read_text())
    assert a["accuracy"] == b["accuracy"]
    assert files_of(work) == files_of(ref) - {"frames.h5"}
    assert not strays(work)


PIPELINE = """\
killed:
  description: ingest -> sfm -> split -> train, small
  vars:
    video: VIDEO
  stages:
    ingest:
      params: {source: "${video}"}
    sfm:
      params: {frames: "${ingest}/frames.h5", threads: 1}
    split:
      params: {input: "${sfm}/posed.h5", every: 4}
    train:
      params: {dataset: "${split}/dataset.h5", preset: test, steps: 120, checkpoint_every: 10,
               threads: 1, no_progress: true}
"""


def kill_in_stage(argv: list[str], cwd: Path, stage_dir: Path, after_s: float) -> None:
    """Start ``dronecap ARGV`` in ``cwd`` and SIGKILL it ``after_s`` seconds after it (re)starts
    the stage of ``stage_dir``: its stamp is written anew with status "running"."""
    stamp = stage_dir / STAMP
    before = stamp.stat().st_mtime_ns if stamp.exists() else None
    p = dronecap(*argv, cwd=cwd)
    while True:
        try:
            fresh = stamp.stat().st_mtime_ns != before and "running" in stamp.read_text()
        except FileNotFoundError:
            fresh = False
        if fresh:
            break
        assert p.poll() is None, f"the run ended before it started {stage_dir.name}"
        time.sleep(0.05)
    time.sleep(after_s)
    p.send_signal(signal.SIGKILL)
    p.wait(timeout=60)


def test_run_killed_anywhere_then_rerun(flight: Path, tmp_path: Path) -> None:
    from dronecap.nerf.trainer import Trainer

    spec = tmp_path / "pipelines.yaml"
    spec.write_text(PIPELINE.replace("VIDEO", str(flight / "flight.mp4")))
    ref, work = tmp_path / "ref", tmp_path / "work"
    ref.mkdir(), work.mkdir()
    argv = ["run", "killed", "--file", str(spec)]
    complete(argv, ref)
    stamps = []
    for stage, after_s in STAGE_KILLS:
        kill_in_stage(argv, work, work / "runs" / "killed" / stage, after_s)
        no_colmap_left(work)
        for p in (work / "runs").rglob("*.h5"):
            same_data(ref / p.relative_to(work), p)
        running = [p.parent.name for p in work.rglob(STAMP) if "running" in p.read_text()]
        stamps += running
    assert {"sfm", "train"} <= set(stamps), f"kills left only {stamps} unfinished"
    complete(argv, work)
    for stage, name in (("ingest", "frames.h5"), ("sfm", "posed.h5"), ("split", "dataset.h5")):
        same_data(ref / "runs" / "killed" / stage / name, work / "runs" / "killed" / stage / name)
    a = Trainer.load(ref / "runs" / "killed" / "train" / "checkpoint.pt")
    b = Trainer.load(work / "runs" / "killed" / "train" / "checkpoint.pt")
    assert a.step == b.step == 120
    wa, wb = a.model_weights(), b.model_weights()
    assert wa.keys() == wb.keys()
    assert all(np.array_equal(wa[k], wb[k]) for k in wa), "resumed model differs"
    assert files_of(work) == files_of(ref)
    assert not strays(work)
