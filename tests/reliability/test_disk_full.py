"""Writers on a full disk, a read-only filesystem, and output paths of the wrong kind.

The full and read-only cases run on a small tmpfs mounted for the test (skipped with the reason
when this process may not mount one). Commands run in a subprocess, so a crash of the HDF5
library (it segfaults on ENOSPC when it writes itself) is a failed test, not a dead test run.
"""

from __future__ import annotations

import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest

from dronecap.datasets import write
from dronecap.datasets.format import Intrinsics, open_dataset, write_dataset
from dronecap.errors import OutputError
from tests.reliability.conftest import random_posed, run_cli, small_dataset

FRAMES = 30  # 30 random 160x160 RGB frames: 2.3 MB, incompressible


@pytest.fixture(scope="module")
def big_posed(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A valid posed.h5 larger than the 1 MB filesystem."""
    ds = random_posed(FRAMES, 3, Intrinsics(150.0, 150.0, 80.0, 80.0, 160, 160))
    return write_dataset(tmp_path_factory.mktemp("big") / "posed.h5", ds)


def _mount(point: Path, options: str) -> None:
    res = subprocess.run(
        ["mount", "-t", "tmpfs", "-o", options, "tmpfs", str(point)],
        capture_output=True,
        text=True,
    )
    if res.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here ({res.stderr.strip() or 'mount failed'})")


@pytest.fixture
def small_fs(tmp_path: Path) -> Iterator[Path]:
    """A 1 MB tmpfs, unmounted after the test."""
    point = tmp_path / "fs"
    point.mkdir()
    _mount(point, "size=1m")
    yield point
    subprocess.run(["umount", "-l", str(point)], check=False)


def cli(*argv: str) -> subprocess.CompletedProcess:
    """``dronecap ARGV`` in a fresh process (a segfault shows as return code -11)."""
    return subprocess.run(
        [sys.executable, "-m", "dronecap.cli", "-q", *argv],
        capture_output=True,
        text=True,
        timeout=120,
    )


def assert_one_line(res: subprocess.CompletedProcess, command: str, *words: str) -> None:
    lines = res.stderr.strip().splitlines()
    assert res.returncode == 1, (res.returncode, res.stderr)
    assert len(lines) == 1 and lines[0].startswith(f"dronecap {command}: error: "), res.stderr
    for w in words:
        assert w in lines[0], lines[0]


def test_split_onto_a_full_disk_is_one_line_and_leaves_nothing(
    big_posed: Path, small_fs: Path
) -> None:
    res = cli("split", str(big_posed), "-o", str(small_fs / "dataset.h5"))
    assert_one_line(res, "split", str(small_fs / "dataset.h5"), "MB free")
    assert list(small_fs.iterdir()) == []


def test_a_full_disk_keeps_the_existing_output(big_posed: Path, small_fs: Path) -> None:
    old = write_dataset(small_fs / "dataset.h5", small_dataset("dataset", 3))
    before = old.read_bytes()
    res = cli("split", str(big_posed), "-o", str(old))
    assert_one_line(res, "split", "MB free")
    assert old.read_bytes() == before
    assert sorted(p.name for p in small_fs.iterdir()) == ["dataset.h5"]


def test_enospc_during_the_write_itself(
    big_posed: Path, small_fs: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Past the free-space check (another writer filled the disk): the write's own ENOSPC is
    one OutputError, the temporary file is removed, the process lives."""
    monkeypatch.setattr(write, "require_free_space", lambda path, nbytes: None)
    with pytest.raises(OutputError, match="no space left on the device") as err:
        write_dataset(small_fs / "dataset.h5", open_dataset(big_posed))
    assert "\n" not in str(err.value)
    assert list(small_fs.iterdir()) == []


def test_shard_onto_a_full_disk_keeps_the_old_shards(
    big_posed: Path, small_fs: Path, tmp_path: Path
) -> None:
    ds = tmp_path / "dataset.h5"
    assert cli("split", str(big_posed), "-o", str(ds)).returncode == 0
    shards = small_fs / "shards"
    shards.mkdir()
    (shards / "summary.json").write_text("{}")
    res = cli("shard", str(ds), "-o", str(shards), "--clients", "2")
    assert_one_line(res, "shard", "MB free")
    assert [p.name for p in small_fs.iterdir()] == ["shards"]
    assert [p.name for p in shards.iterdir()] == ["summary.json"]


def test_read_only_filesystem(small_files: dict[str, Path], tmp_path: Path) -> None:
    point = tmp_path / "ro"
    point.mkdir()
    _mount(point, "size=1m,ro")
    try:
        for command, out in (("split", point / "d.h5"), ("shard", point / "shards")):
            src = small_files["posed" if command == "split" else "dataset"]
            res = run_cli(
                [command, str(src), "-o", str(out), *(["--clients", "2"] * (command == "shard"))]
            )
            assert res.one_line_error(command), res
            assert "read-only filesystem" in res.err
        assert list(point.iterdir()) == []
    finally:
        subprocess.run(["umount", "-l", str(point)], check=False)


@pytest.mark.parametrize(
    ("command", "kind", "make", "message"),
    [
        ("split", "posed", "dir", "is a folder, expected a file"),
        ("split", "posed", "under_file", "is a file, not a folder"),
        ("shard", "dataset", "file", "is a file, expected a folder"),
        ("shard", "dataset", "under_file", "a file is in the way of a folder"),
    ],
)
def test_output_paths_of_the_wrong_kind(
    small_files: dict[str, Path], tmp_path: Path, command: str, kind: str, make: str, message: str
) -> None:
    out = tmp_path / "out"
    if make == "dir":
        out.mkdir()
        (out / "keep.txt").write_text("mine")
    elif make == "file":
        out.write_text("mine")
    else:
        (tmp_path / "plain").write_text("mine")
        out = tmp_path / "plain" / "out"
    extra = ["--clients", "2"] if command == "shard" else []
    res = run_cli([command, str(small_files[kind]), "-o", str(out), *extra])
    assert res.one_line_error(command), res
    assert message in res.err
    if make == "dir":
        assert [p.name for p in out.iterdir()] == ["keep.txt"]
    elif make == "file":
        assert out.read_text() == "mine"
    assert not [p for p in tmp_path.rglob(".*tmp-*")]


def test_export_transforms_onto_a_full_disk(big_posed: Path, small_fs: Path) -> None:
    res = cli("export-transforms", str(big_posed), "-o", str(small_fs / "tr"))
    assert_one_line(res, "export-transforms", "no space")
    assert list(small_fs.iterdir()) == []


def test_simulate_on_a_full_disk_leaves_no_video(small_fs: Path) -> None:
    """FFmpeg's writes fail silently on a full disk: the video is checked before it is put in
    place, so no undecodable flight.mp4 is left."""
    res = cli("simulate", "--frames", "150", "-o", str(small_fs / "flight.mp4"))
    assert res.returncode == 1, res.stderr
    assert "no space left on the device" in res.stderr, res.stderr
    assert not (small_fs / "flight.mp4").exists()
    assert not [p for p in small_fs.iterdir() if ".tmp-" in p.name]
