"""Two commands writing one output at once: one proceeds, the other stops in one line (or, with
``dronecap --wait``, says that it waits and then runs), and the output equals a single run's.

Every case uses real processes: the lock is an ``flock``, which only means something between
processes.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from dronecap.datasets.format import open_dataset, write_dataset
from dronecap.files import lock_path, output_lock
from tests.reliability.conftest import dronecap, small_dataset


def _start(*argv: str, cwd: Path) -> subprocess.Popen:
    """``dronecap -q ARGV`` in ``cwd``, importing dronecap from this checkout, no progress."""
    env = {**os.environ, "DRONECAP_PROGRESS": "off", "PYTHONPATH": os.getcwd()}
    return dronecap(*argv, cwd=cwd, env=env)


def test_second_writer_stops_in_one_line(small_files, tmp_path: Path) -> None:
    out = tmp_path / "split.h5"
    with output_lock(out):
        p = _start("split", str(small_files["posed"]), "-o", str(out), cwd=tmp_path)
        _, err = p.communicate(timeout=120)
    assert p.returncode == 1, err
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("dronecap split: error: "), err
    assert f"being written by another dronecap command (pid {os.getpid()})" in lines[0]
    assert not out.exists()
    assert not lock_path(out).exists()


def test_waiting_writer_says_so_then_writes_a_single_runs_output(small_files, tmp_path) -> None:
    alone = tmp_path / "alone.h5"
    p = _start("split", str(small_files["posed"]), "-o", str(alone), cwd=tmp_path)
    assert p.wait(timeout=120) == 0
    out = tmp_path / "split.h5"
    with output_lock(out):
        p = _start("--wait", "split", str(small_files["posed"]), "-o", str(out), cwd=tmp_path)
        time.sleep(4)
        assert p.poll() is None  # still waiting
        assert not out.exists()
    _, err = p.communicate(timeout=120)
    assert p.returncode == 0, err
    assert f"waiting for pid {os.getpid()}, which is writing {out}" in err
    a, b = open_dataset(alone), open_dataset(out)
    assert np.array_equal(a.split, b.split) and np.array_equal(a.images, b.images)


def test_four_splits_at_once(small_files, tmp_path: Path) -> None:
    """The issue's case: four `split` into one output. Exactly the ones that got the lock write;
    every other says it is locked; the output is a valid split of the input."""
    out = tmp_path / "split.h5"
    procs = [_start("split", str(small_files["posed"]), "-o", str(out), cwd=tmp_path)
             for _ in range(4)]  # fmt: skip
    errs = [p.communicate(timeout=300)[1] for p in procs]
    codes = [p.returncode for p in procs]
    assert codes.count(0) >= 1, errs
    for code, err in zip(codes, errs, strict=True):
        assert code == 0 or "being written by another dronecap command" in err, err
    assert open_dataset(out).n == open_dataset(small_files["posed"]).n


@pytest.mark.slow
def test_two_trains_into_one_run_folder(tmp_path: Path) -> None:
    """Two `train` on different datasets into one --out: the second stops at once; the folder
    is the first run's alone (run.json and metrics.json agree)."""
    a = write_dataset(tmp_path / "a.h5", small_dataset("dataset", 3))
    other = small_dataset("dataset", 3)
    other.images = 255 - other.images
    b = write_dataset(tmp_path / "b.h5", other)
    common = ["--preset", "test", "--threads", "1", "--backend", "torch", "--out", "run"]
    first = _start("train", str(a), "--steps", "30", *common, cwd=tmp_path)
    lock = lock_path(tmp_path / "run")
    t0 = time.monotonic()
    while not lock.exists() and time.monotonic() - t0 < 120:
        time.sleep(0.2)
    second = _start("train", str(b), "--steps", "5", *common, cwd=tmp_path)
    _, err2 = second.communicate(timeout=300)
    _, err1 = first.communicate(timeout=900)
    assert first.returncode == 0, err1
    assert second.returncode == 1 and "being written by another dronecap command" in err2, err2
    info = json.loads((tmp_path / "run" / "run.json").read_text())
    assert Path(info["dataset"]).name == "a.h5"
    assert (tmp_path / "run" / "metrics.json").exists()


def test_waiting_for_another_kernel_build_is_said(tmp_path: Path) -> None:
    """A process that finds the kernel build folder locked (another process building) says on
    stderr that it waits, and for whom, then goes on once the lock is released."""
    import fcntl

    from dronecap.nerf.backend import KERNELS, WAIT_NOTICE, build_dir

    name = next(iter(KERNELS))
    folder = build_dir(name)
    folder.mkdir(parents=True, exist_ok=True)
    code = "import contextlib\nfrom dronecap.nerf.backend import load\n"
    code += f"with contextlib.suppress(Exception):\n    load({name!r})\n"
    with open(folder / ".dronecap-build.lock", "a+") as guard:
        fcntl.flock(guard, fcntl.LOCK_EX)
        guard.seek(0)
        guard.truncate()
        guard.write(str(os.getpid()))
        guard.flush()
        p = subprocess.Popen([sys.executable, "-c", code], stderr=subprocess.PIPE, text=True,
                             env={**os.environ, "PYTHONPATH": os.getcwd()})  # fmt: skip
        line = p.stderr.readline()
        assert line.strip() == f"{WAIT_NOTICE} (pid {os.getpid()})"
        assert p.poll() is None
    p.communicate(timeout=600)
    assert p.returncode == 0
