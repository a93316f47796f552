"""A damaged version 1 file (no checksums) that crashes or hangs HDF5 is a one-line error.

``open_dataset`` reads files without the checksummed superblock in a forked child first
(:mod:`dronecap.datasets.probe`). The damaged bytes below were found with the bit flip scan of
``benchmarks/reliability.py`` on the small v1 file of :func:`small_dataset`; each test first
checks that a plain read of its file still dies (HDF5's layout of that file is deterministic,
only the creation time in the provenance changes), so a test cannot pass on a harmless flip.
"""

from __future__ import annotations

import faulthandler
import os
import signal
from pathlib import Path

import pytest

from dronecap.datasets import probe
from dronecap.datasets.format import DatasetError, open_dataset, write_dataset
from dronecap.datasets.read import _read_dataset
from tests.reliability.conftest import as_version_1, run_cli, small_dataset

# byte -> what it holds; HDF5 segfaults on the flipped file, or loops (> 40 s, never ended)
CRASHES = {1089: "datatype of the root's format attribute", 20865: "object header of names"}
HANGS = {2057: "size of the global heap collection (the variable-length strings)"}


@pytest.fixture(scope="module")
def v1_file(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The small dataset in the version 1 layout (25232 bytes)."""
    root = tmp_path_factory.mktemp("v1")
    return as_version_1(write_dataset(root / "v2.h5", small_dataset("dataset", 3)), root / "v1.h5")


def flipped(src: Path, pos: int, dst: Path) -> Path:
    """``src`` with bit ``pos % 8`` of byte ``pos`` flipped (the benchmark's scan), at ``dst``."""
    raw = bytearray(src.read_bytes())
    raw[pos] ^= 1 << (pos % 8)
    dst.write_bytes(bytes(raw))
    return dst


def plain_read_signal(path: Path, limit_s: int) -> int | None:
    """The signal that ends a read of ``path`` without the probe, in a forked child (SIGALRM
    after ``limit_s`` seconds: a hang); None when the read returns or raises."""
    pid = os.fork()
    if pid == 0:
        faulthandler.disable()  # pytest's would print the crash
        signal.signal(signal.SIGALRM, signal.SIG_DFL)
        signal.alarm(limit_s)
        try:
            _read_dataset(path, None)
        finally:
            os._exit(0)
    _, status = os.waitpid(pid, 0)
    return os.WTERMSIG(status) if os.WIFSIGNALED(status) else None


def assert_one_line(err: pytest.ExceptionInfo, path: Path, what: str) -> None:
    msg = str(err.value)
    assert "\n" not in msg and str(path) in msg and what in msg, msg


@pytest.mark.parametrize("pos", sorted(CRASHES))
def test_a_flip_that_crashes_hdf5_is_a_one_line_error(v1_file: Path, tmp_path: Path, pos: int):
    bad = flipped(v1_file, pos, tmp_path / "bad.h5")
    assert plain_read_signal(bad, 30) == signal.SIGSEGV, f"byte {pos} no longer crashes HDF5"
    with pytest.raises(DatasetError) as err:
        open_dataset(bad)
    assert_one_line(err, bad, "reading it crashed the HDF5 library (SIGSEGV)")
    out = run_cli(["split", str(bad), "-o", str(tmp_path / "split.h5")])
    assert out.one_line_error("split"), out.err
    assert not (tmp_path / "split.h5").exists()


@pytest.mark.parametrize("pos", sorted(HANGS))
def test_a_flip_that_hangs_hdf5_is_a_one_line_error(
    v1_file: Path, tmp_path: Path, pos: int, monkeypatch: pytest.MonkeyPatch
) -> None:
    bad = flipped(v1_file, pos, tmp_path / "bad.h5")
    assert plain_read_signal(bad, 2) == signal.SIGALRM, f"byte {pos} no longer hangs HDF5"
    monkeypatch.setattr(probe, "PROBE_S", 1.0)  # the file reads in ~10 ms when whole
    with pytest.raises(DatasetError) as err:
        open_dataset(bad)
    assert_one_line(err, bad, "still reading after 1 s")


def test_only_files_without_checksums_are_probed(v1_file: Path, tmp_path: Path) -> None:
    v2 = v1_file.parent / "v2.h5"
    assert probe.checksummed_layout(v2)
    assert not probe.checksummed_layout(v1_file)
    assert not probe.checksummed_layout(flipped(v2, 8, tmp_path / "v0.h5"))  # superblock 3 -> 2
    (tmp_path / "short.h5").write_bytes(b"\x89HDF")
    assert not probe.checksummed_layout(tmp_path / "short.h5")
    assert open_dataset(v1_file).same_as(open_dataset(v2))  # a whole v1 file passes the probe
