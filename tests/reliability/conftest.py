"""Small valid files for the reliability tests, and the CLI run in process with its outcome.

The files are a ring of 12 cameras (OpenCV axes) looking at a box at the origin: ``posed.h5``
(gray 10x12, no split) and ``dataset.h5`` (RGB + alpha, every 4th frame in test), both with
every field the stages read, so a mutation of any of them can be tried.
"""

from __future__ import annotations

import contextlib
import dataclasses
import io
import signal
import subprocess
import sys
import time
import traceback
from dataclasses import dataclass
from pathlib import Path

import h5py
import numpy as np
import pytest

from dronecap.cli import main
from dronecap.datasets.format import Dataset, Intrinsics, provenance, write_dataset

N, H, W = 12, 10, 12
KILL_FRACTIONS = (0.2, 0.4, 0.6, 0.8, 0.95)  # kill -9 points, in parts of an uninterrupted run
AABB = np.array([[-0.5, -0.5, -0.5], [0.5, 0.5, 0.5]])


def ring_poses(n: int = N, radius: float = 3.0, height: float = 0.6) -> np.ndarray:
    """Camera-to-world [n, 4, 4], OpenCV axes, on a ring about +z looking at the origin."""
    poses = np.tile(np.eye(4), (n, 1, 1))
    for i, a in enumerate(np.linspace(0, 2 * np.pi, n, endpoint=False)):
        eye = np.array([radius * np.cos(a), radius * np.sin(a), height])
        z = -eye / np.linalg.norm(eye)
        x = np.cross(z, [0.0, 0.0, 1.0])
        x /= np.linalg.norm(x)
        y = np.cross(z, x)
        poses[i, :3, :3] = np.stack([x, y, z], 1)
        poses[i, :3, 3] = eye
    return poses


def random_posed(n: int, seed: int, intrinsics: Intrinsics) -> Dataset:
    """A valid posed flight of ``n`` random (incompressible) 160x160 RGB frames on a ring, seen
    through ``intrinsics``."""
    rng = np.random.default_rng(seed)
    poses = ring_poses(n)
    dist = np.linalg.norm(poses[:, :3, 3], axis=1)
    return dataclasses.replace(
        small_dataset("posed", 3),
        images=rng.integers(0, 256, (n, 160, 160, 3), dtype=np.uint8),
        poses=poses,
        intrinsics=intrinsics,
        names=None,
        source_index=None,
        timestamps=None,
        near_far=np.stack([dist - 1, dist + 1], 1),
        extra={},
    )


def small_dataset(kind: str, channels: int) -> Dataset:
    """A valid file's contents of ``kind`` with ``channels`` image channels."""
    rng = np.random.default_rng(7)
    poses = ring_poses()
    dist = np.linalg.norm(poses[:, :3, 3], axis=1)
    ds = Dataset(
        images=rng.integers(0, 256, (N, H, W, channels), dtype=np.uint8),
        kind=kind,
        poses=poses,
        intrinsics=Intrinsics(11.0, 11.0, 6.0, 5.0, W, H),
        names=[f"frame_{i:03d}.png" for i in range(N)],
        source_index=np.arange(N) * 3,
        timestamps=np.arange(N) / 10.0,
        near_far=np.stack([dist - 1.0, dist + 1.0], 1),
        aabb=AABB.copy(),
        normalization=np.eye(4),
        extra={"sharpness": rng.random(N)},
        provenance=provenance("test", {"seed": 7}, {}),
        attrs={"scene": "ring"},
    )
    if kind == "dataset":
        ds.split = np.where(np.arange(N) % 4 == 0, 2, 0).astype(np.int8)
        ds.alpha = rng.integers(0, 256, (N, H, W), dtype=np.uint8)
        ds.background = (0.0,) * channels
    return ds


def as_version_1(src: Path, dst: Path) -> Path:
    """The contents of ``src`` in the version 1 layout: no filters but lzf on images/alpha,
    HDF5's default (oldest) metadata layout, variable-length strings, format_version 1."""
    with h5py.File(src, "r") as f, h5py.File(dst, "w") as g:
        for k, v in f.attrs.items():
            g.attrs[k] = v.decode() if isinstance(v, bytes) else v
        g.attrs["format_version"] = 1

        def copy(name: str, obj: object) -> None:
            if not isinstance(obj, h5py.Dataset):
                return
            data = obj[()]
            if data.dtype.kind == "S":
                data = np.array([s.decode() for s in data], dtype=h5py.string_dtype())
            lzf = name in ("images", "alpha") and data.size
            g.create_dataset(
                name,
                data=data,
                chunks=(1, *data.shape[1:]) if lzf else None,
                compression="lzf" if lzf else None,
            )

        f.visititems(copy)
    return dst


@pytest.fixture(autouse=True)
def _no_progress(monkeypatch: pytest.MonkeyPatch) -> None:
    """No progress lines on stderr: the tests count the error lines."""
    monkeypatch.setenv("DRONECAP_PROGRESS", "off")


@pytest.fixture(scope="session")
def small_files(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """{"posed": posed.h5, "dataset": dataset.h5}: small valid files (never modified)."""
    root = tmp_path_factory.mktemp("small")
    return {
        "posed": write_dataset(root / "posed.h5", small_dataset("posed", 1)),
        "dataset": write_dataset(root / "dataset.h5", small_dataset("dataset", 3)),
    }


@dataclass
class Outcome:
    """What a command did: exit code, stderr, and the traceback of an escaped exception."""

    code: int | None
    err: str
    crash: str | None = None

    def one_line_error(self, command: str) -> bool:
        """True when it failed cleanly: exit 1 or 2 (argparse) and one error line for the user
        (argparse prints its usage before that line)."""
        lines = [ln for ln in self.err.splitlines() if ln.strip()]
        return (
            self.crash is None
            and self.code in (1, 2)
            and bool(lines)
            and lines[-1].startswith(f"dronecap {command}: error: ")
            and "Traceback" not in self.err
            and (self.code == 2 or len(lines) == 1)
        )


class Hang(Exception):
    """A command took longer than its alarm."""


def run_cli(argv: list[str], timeout_s: int = 60) -> Outcome:
    """Run ``dronecap ARGV`` in this process; an escaped exception or SystemExit is caught and
    kept; a run longer than ``timeout_s`` raises :class:`Hang`."""

    def alarm(signum: int, frame: object) -> None:
        raise Hang(f"dronecap {' '.join(argv)} ran longer than {timeout_s} s")

    err = io.StringIO()
    old = signal.signal(signal.SIGALRM, alarm)
    signal.alarm(timeout_s)
    try:
        with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
            code = main(argv)
        return Outcome(code, err.getvalue())
    except SystemExit as ex:
        return Outcome(int(ex.code or 0), err.getvalue())
    except Hang:
        raise
    except BaseException:  # noqa: BLE001  (the point: nothing may escape the CLI)
        return Outcome(None, err.getvalue(), traceback.format_exc())
    finally:
        signal.alarm(0)
        signal.signal(signal.SIGALRM, old)


def dronecap(*argv: str, cwd: Path, env: dict[str, str] | None = None) -> subprocess.Popen:
    """``dronecap -q ARGV`` started in a fresh process in ``cwd`` (stderr kept for the test),
    with environment ``env`` (default: this one's)."""
    return subprocess.Popen(
        [sys.executable, "-m", "dronecap.cli", "-q", *argv],
        cwd=cwd,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        text=True,
        env=env,
    )


def complete(argv: list[str], cwd: Path) -> float:
    """Run ``dronecap ARGV`` to the end (it must succeed); its wall time in seconds."""
    t0 = time.perf_counter()
    p = dronecap(*argv, cwd=cwd)
    _, err = p.communicate(timeout=1200)
    assert p.returncode == 0, err
    return time.perf_counter() - t0


def kill_at(argv: list[str], cwd: Path, delay_s: float) -> None:
    """Start ``dronecap ARGV`` and SIGKILL it after ``delay_s`` seconds (if still running)."""
    p = dronecap(*argv, cwd=cwd)
    time.sleep(delay_s)
    p.send_signal(signal.SIGKILL)
    p.wait(timeout=60)


def strays(root: Path) -> list[Path]:
    """Temporary files of :func:`dronecap.files.atomic_output` left under ``root``."""
    return [p for p in root.rglob("*") if ".tmp-" in p.name or ".old-" in p.name]
