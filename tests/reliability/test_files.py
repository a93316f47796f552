"""atomic_output on every path (success, errors, Ctrl-C, a killed writer's leftovers), the
storage-error reading of OSErrors, and the option range check."""

from __future__ import annotations

import errno
import os
import subprocess
import sys
from pathlib import Path

import pytest

from dronecap.errors import InputError, OutputError, check_option
from dronecap.files import atomic_output, storage_error


@pytest.mark.parametrize("exc", [RuntimeError("boom"), KeyboardInterrupt()])
def test_failed_block_removes_the_temporary_and_keeps_the_old_output(
    tmp_path: Path, exc: BaseException
) -> None:
    out = tmp_path / "a.txt"
    out.write_text("old")
    with pytest.raises(type(exc)), atomic_output(out) as tmp:
        tmp.write_text("partial")
        raise exc
    assert out.read_text() == "old"
    assert [p.name for p in tmp_path.iterdir()] == ["a.txt"]


def test_folder_output_replaces_a_folder_only(tmp_path: Path) -> None:
    folder = tmp_path / "shards"
    folder.mkdir()
    (folder / "a.h5").write_text("x")
    with atomic_output(folder) as tmp:
        tmp.mkdir()
        (tmp / "a.h5").write_text("y")
        (tmp / "b.h5").write_text("z")
    assert sorted(p.name for p in folder.iterdir()) == ["a.h5", "b.h5"]
    assert (folder / "a.h5").read_text() == "y"
    with pytest.raises(OutputError, match="is a folder, expected a file"):
        with atomic_output(folder) as tmp:
            tmp.write_text("a file")
    assert sorted(p.name for p in folder.iterdir()) == ["a.h5", "b.h5"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["shards"]


def test_a_folder_holding_other_files_is_not_replaced(tmp_path: Path) -> None:
    ws = tmp_path / "workspace"
    ws.mkdir()
    (ws / "dataset.h5").write_text("the user's input")
    (ws / "transforms.json").write_text("old output")
    with pytest.raises(OutputError, match=r"holds dataset.h5, which this output does not write"):
        with atomic_output(ws) as tmp:
            tmp.mkdir()
            (tmp / "transforms.json").write_text("new output")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["workspace"]
    assert (ws / "transforms.json").read_text() == "old output"
    with atomic_output(ws, replaceable=lambda name: name.endswith(".h5")) as tmp:
        tmp.mkdir()
        (tmp / "transforms.json").write_text("new output")
    assert [p.name for p in ws.iterdir()] == ["transforms.json"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["workspace"]


def test_a_folder_set_aside_by_a_killed_writer_is_put_back(tmp_path: Path) -> None:
    """Killed between moving the old folder aside and renaming the new one in: the next writer
    restores the old folder first, then replaces it as usual."""
    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], text=True,
                          capture_output=True, check=True)  # fmt: skip
    aside = tmp_path / f".shards.old-{int(dead.stdout)}"
    aside.mkdir()
    (aside / "client_0.h5").write_text("old")
    with pytest.raises(RuntimeError), atomic_output(tmp_path / "shards"):
        raise RuntimeError("this writer fails too")
    assert [p.name for p in tmp_path.iterdir()] == ["shards"]
    assert (tmp_path / "shards" / "client_0.h5").read_text() == "old"


def test_leftovers_of_a_killed_writer_are_removed_not_those_of_a_live_one(tmp_path: Path) -> None:
    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], text=True,
                          capture_output=True, check=True)  # fmt: skip
    dead_pid = int(dead.stdout)  # that process has exited
    live = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    try:
        stale = tmp_path / f".d.h5.tmp-{dead_pid}"
        busy = tmp_path / f".d.h5.tmp-{live.pid}"
        stale.write_text("half")
        busy.mkdir()
        with atomic_output(tmp_path / "d.h5") as tmp:
            tmp.write_text("done")
        assert sorted(p.name for p in tmp_path.iterdir()) == [busy.name, "d.h5"]
    finally:
        live.kill()
        live.wait()


def test_storage_errors_are_read_from_errno_or_from_h5py_text() -> None:
    assert storage_error(OSError(errno.ENOSPC, "x")) == "no space left on the device"
    assert storage_error(OSError(errno.EROFS, "x")) == "read-only filesystem"
    h5 = OSError("Unable to synchronously create file (unable to open file: name = 'a.h5', "
                 "errno = 30, error message = 'Read-only file system')")  # fmt: skip
    assert storage_error(h5) == "read-only filesystem"
    assert storage_error(OSError(errno.ENOENT, "x")) is None
    assert storage_error(ValueError("errno = 28")) is None


def test_storage_error_outside_atomic_output_is_one_cli_line(tmp_path: Path, capsys) -> None:
    """An OSError of the storage raised by a command's own mkdir: one line, exit 1."""
    from dronecap.cli import main

    (tmp_path / "file").write_text("x")
    out = tmp_path / "file" / "run"
    code = main(["federate", str(tmp_path), "--clients", "1", "--out", str(out)])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 1 and len(err) == 1 and err[0].startswith("dronecap federate: error: ")
    assert os.fspath(tmp_path / "file") in err[0]


@pytest.mark.parametrize(
    ("value", "lo", "hi", "ok"),
    [
        (0, 0, None, True),
        (-1, 0, None, False),
        (float("nan"), 0, None, False),
        (float("inf"), 0, None, False),
        (0.5, 0.0, 0.999, True),
        (1.0, 0.0, 0.999, False),
        (True, 0, None, False),
        ("3", 0, None, False),
    ],
)
def test_check_option(value, lo, hi, ok: bool) -> None:
    if ok:
        check_option("--x", value, lo, hi)
    else:
        with pytest.raises(InputError, match=r"^--x must be .*, got "):
            check_option("--x", value, lo, hi)
