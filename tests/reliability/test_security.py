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


def test_train_resume_from_malicious_checkpoint(
    trained: Path, small_files: dict[str, Path], tmp_path: Path
) -> None:
    run, marker = _evil_run(trained, tmp_path)
    argv = ["train", str(small_files["dataset"]), "--resume-from", str(run), "--preset", "test"]
    res = run_cli([*argv, "--threads", "1", "--backend", "torch", "--out", str(tmp_path / "o")])
    assert res.one_line_error("train"), res
    assert "refusing to load" in res.err and not marker.exists()


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


_SIM = "{command: simulate, params: {scene: corridor, frames: 3}}"


@pytest.mark.parametrize(
    ("yaml_text", "name", "message"),
    [
        (f"p:\n  stages:\n    '../../victim': {_SIM}\n", "p", "stage name '../../victim'"),
        (f"'../x':\n  stages:\n    s: {_SIM}\n", "../x", "pipeline name '../x'"),
        (f"'/abs':\n  stages:\n    s: {_SIM}\n", "/abs", "pipeline name '/abs'"),
        (f"p:\n  stages:\n    'a/b': {_SIM}\n", "p", "stage name 'a/b'"),
        (f"p:\n  stages:\n    '..': {_SIM}\n", "p", "stage name '..'"),
        ("p:\n  stages:\n    s: {command: simulate, params: {scene: !!python/object/apply:os.sys"
         "tem ['touch MARKER'], frames: 3}}\n", "p", "tag !!python/object/apply:os.system"),
        (f"p:\n  stages:\n    '$(touch MARKER)': {_SIM}\n", "p", "stage name '$(touch MARKER)'"),
    ],
)  # fmt: skip
def test_hostile_pipeline_is_refused_before_anything(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, yaml_text: str, name: str, message: str
) -> None:
    """Names that would leave the runs folder, Python tags, shell text: one line, nothing run,
    the folder a stage name points at untouched."""
    work = tmp_path / "a" / "b"
    (work / "runs").mkdir(parents=True)
    victim = tmp_path / "victim"
    victim.mkdir()
    (victim / "keep.txt").write_text("mine")
    (work / "pipelines.yaml").write_text(yaml_text)
    monkeypatch.chdir(work)
    res = run_cli(["run", name, "--file", "pipelines.yaml", "--runs", "runs"])
    assert res.one_line_error("run"), res
    assert message in res.err, res.err
    assert (victim / "keep.txt").read_text() == "mine"
    assert not (work / "MARKER").exists()
    assert sorted(p.name for p in work.rglob("*")) == ["pipelines.yaml", "runs"]


def test_stage_folder_linked_out_of_runs_is_refused(tmp_path: Path) -> None:
    victim = tmp_path / "victim"
    victim.mkdir()
    (victim / "keep.txt").write_text("mine")
    (tmp_path / "pipelines.yaml").write_text(f"p:\n  stages:\n    s: {_SIM}\n")
    (tmp_path / "runs" / "p").mkdir(parents=True)
    (tmp_path / "runs" / "p" / "s").symlink_to(victim)
    res = run_cli(["run", "p", "--file", str(tmp_path / "pipelines.yaml"), "--runs",
                   str(tmp_path / "runs")])  # fmt: skip
    assert res.one_line_error("run"), res
    assert "leaves the runs folder" in res.err
    assert (victim / "keep.txt").read_text() == "mine"
