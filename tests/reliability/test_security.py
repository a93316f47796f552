"""Files from elsewhere never run code: checkpoints, pipelines.yaml, HDF5 links, imported paths.

A malicious checkpoint here is a real pickle whose ``__reduce__`` would create a marker file; the
commands that open a run folder must refuse it in one line without creating the marker.
"""

from __future__ import annotations

import os
import pathlib
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from dronecap.nerf.checkpoint import main as convert_main
from dronecap.nerf.checkpoint import read_checkpoint
from tests.reliability.conftest import run_cli


class _Payload:
    """Unpickling this runs ``touch MARKER``."""

    def __init__(self, marker: Path) -> None:
        self.marker = marker

    def __reduce__(self):
        return (os.system, (f"touch {self.marker}",))


@pytest.fixture(scope="module")
def trained(small_files: dict[str, Path], tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A real 2-step run folder of the small dataset."""
    out = tmp_path_factory.mktemp("run") / "run"
    argv = ["train", str(small_files["dataset"]), "--preset", "test", "--steps", "2"]
    res = run_cli([*argv, "--threads", "1", "--backend", "torch", "--out", str(out)], 300)
    assert res.code == 0, res
    return out


def _evil_run(trained: Path, tmp: Path) -> tuple[Path, Path]:
    run, marker = tmp / "evil", tmp / "MARKER"
    shutil.copytree(trained, run)
    torch.save({"version": 1, "field": _Payload(marker)}, run / "checkpoint.pt")
    return run, marker


@pytest.mark.parametrize("command", ["eval", "render", "export-geometry"])
def test_malicious_checkpoint_is_refused(trained: Path, tmp_path: Path, command: str) -> None:
    run, marker = _evil_run(trained, tmp_path)
    p = subprocess.run(
        [sys.executable, "-m", "dronecap.cli", "-q", command, str(run)],
        capture_output=True,
        text=True,
        timeout=300,
        env={**os.environ, "DRONECAP_PROGRESS": "off"},
    )
    assert p.returncode == 1, p.stderr
    assert not marker.exists()
    lines = [ln for ln in p.stderr.splitlines() if ln.startswith(f"dronecap {command}: error: ")]
    assert len(lines) == 1 and "refusing to load" in lines[0], p.stderr
    assert "python -m dronecap.nerf.checkpoint --trust" in lines[0]
    assert "Traceback" not in p.stderr


def test_train_resume_from_malicious_checkpoint(trained: Path, tmp_path: Path) -> None:
    run, marker = _evil_run(trained, tmp_path)
    res = run_cli(["train", "--resume-from", str(run), "--out", str(tmp_path / "o"), "--preset",
                   "test", "--threads", "1", str(trained.parent / "nope.h5")])  # fmt: skip
    assert res.code in (1, 2) and not marker.exists(), res


def test_checkpoint_round_trip_is_plain_data(trained: Path) -> None:
    """What train writes loads with weights_only=True and no allowed globals at all."""
    ck = torch.load(trained / "checkpoint.pt", weights_only=True)
    assert ck["version"] == 1
    assert read_checkpoint(trained / "checkpoint.pt")["grid"]["density"].dtype.kind == "f"


def test_trusted_old_checkpoint_converts(trained: Path, tmp_path: Path) -> None:
    """A file holding an object outside the allowed set is refused; once converted by the user
    (who trusts it) it loads the safe way."""
    ck = torch.load(trained / "checkpoint.pt", weights_only=True)
    ck["note"] = pathlib.PurePosixPath("a/b")
    path = tmp_path / "checkpoint.pt"
    torch.save(ck, path)
    with pytest.raises(Exception, match="refusing to load"):
        read_checkpoint(path)
    assert convert_main([str(path), "--trust"]) == 0
    assert read_checkpoint(path)["step"] == 2
