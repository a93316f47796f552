"""A catalogue of bad inputs per command (split, shard, federate), run in process.

Each case must end with one error line naming the problem (argparse's own errors: exit 2 after
its usage line), before any work starts, and leave no output behind.
"""

from __future__ import annotations

import dataclasses
import shutil
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

from dronecap.datasets.format import open_dataset, write_dataset
from dronecap.datasets.shard import shard_dataset
from tests.reliability.conftest import run_cli

# A case builds its argv from (small files, a scratch folder) and names a fragment of the message.
Case = tuple[str, Callable[[dict[str, Path], Path], list[str]], str]


def _with_split(files: dict[str, Path], tmp: Path, split: list[int]) -> Path:
    ds = open_dataset(files["dataset"])
    ds.split = np.resize(np.array(split, np.int8), ds.n)
    return write_dataset(tmp / "custom.h5", ds)


def _one_frame(files: dict[str, Path], tmp: Path) -> Path:
    return write_dataset(tmp / "one.h5", open_dataset(files["posed"]).subset([0]))


def _frames_only(files: dict[str, Path], tmp: Path) -> Path:
    ds = open_dataset(files["posed"])
    ds = dataclasses.replace(ds, kind="frames", poses=None, near_far=None, aabb=None)
    return write_dataset(tmp / "frames.h5", ds)


def _text_file(tmp: Path) -> Path:
    (tmp / "notes.h5").write_text("not a dataset\n")
    return tmp / "notes.h5"


SPLIT: list[Case] = [
    ("every 1", lambda f, t: [str(f["posed"]), "--every", "1"], "--every must be >= 2"),
    ("every -3", lambda f, t: [str(f["posed"]), "--every", "-3"], "--every must be >= 2"),
    ("every x", lambda f, t: [str(f["posed"]), "--every", "x"], "invalid int value"),
    ("missing input", lambda f, t: [str(t / "nope.h5")], "no such file"),
    ("input is a folder", lambda f, t: [str(t)], "is a folder"),
    ("input is text", lambda f, t: [str(_text_file(t))], "not a readable HDF5 file"),
    ("input is a device", lambda f, t: ["/dev/zero"], "is not a regular file"),
    ("frames, no poses", lambda f, t: [str(_frames_only(f, t))], "expected one of"),
    ("one frame", lambda f, t: [str(_one_frame(f, t))], "leaves no train frame"),
    ("all test", lambda f, t: [str(_with_split(f, t, [2]))], "leaves no train frame"),
    ("all train", lambda f, t: [str(_with_split(f, t, [0]))], "leaves no test frame"),
]

SHARD: list[Case] = [
    ("clients 0", lambda f, t: [str(f["dataset"]), "--clients", "0"], "--clients must be >= 1"),
    ("clients -1", lambda f, t: [str(f["dataset"]), "--clients", "-1"], "--clients must be"),
    ("seed -1", lambda f, t: [str(f["dataset"]), "--seed", "-1"], "--seed must be >= 0"),
    ("scheme", lambda f, t: [str(f["dataset"]), "--scheme", "rings"], "--scheme must be one of"),
    ("too many", lambda f, t: [str(f["dataset"]), "--clients", "50"], "need at least 50 train"),
    ("posed input", lambda f, t: [str(f["posed"])], "expected one of ['dataset']"),
    ("no test", lambda f, t: [str(_with_split(f, t, [0]))], "has no test frames"),
    ("missing input", lambda f, t: [str(t / "nope.h5")], "no such file"),
    ("into a workspace", lambda f, t: [str(f["dataset"]), "-o", str(f["dataset"].parent)],
     "holds files that are not shards (dataset.h5, posed.h5)"),
]  # fmt: skip


@pytest.fixture(scope="module")
def shards(small_files: dict[str, Path], tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Two IID shards of the small dataset (never modified)."""
    return shard_dataset(small_files["dataset"], tmp_path_factory.mktemp("sh") / "shards", 2, "iid")


def _shard_copy(shards: Path, tmp: Path, damage: str) -> Path:
    out = tmp / "shards"
    shutil.copytree(shards, out)
    target = out / "client_1.h5"
    if damage == "flip":
        b = bytearray(target.read_bytes())
        b[len(b) // 2] ^= 0x10
        target.write_bytes(bytes(b))
    elif damage == "missing":
        target.unlink()
    elif damage == "renamed":
        target.rename(out / "client_7.h5")
    elif damage == "no_train":
        ds = open_dataset(target)
        ds.split[:] = 2
        write_dataset(target, ds)
    return out


def federate_cases(shards: Path) -> list[Case]:
    ok = [str(shards), "--clients", "2", "--preset", "test"]

    def opt(*extra: str) -> Callable[[dict[str, Path], Path], list[str]]:
        return lambda f, t: [*ok, "--out", str(t / "run"), *extra]

    def damaged(kind: str) -> Callable[[dict[str, Path], Path], list[str]]:
        return lambda f, t: [str(_shard_copy(shards, t, kind)), *ok[1:], "--out", str(t / "run")]

    return [
        ("round-timeout 0", opt("--round-timeout", "0"), "--round-timeout must be >= 1"),
        ("round-timeout nan", opt("--round-timeout", "nan"), "--round-timeout must be >= 1"),
        ("rounds 0", opt("--rounds", "0"), "--rounds must be >= 1"),
        ("local-steps 0", opt("--local-steps", "0"), "--local-steps must be >= 1"),
        ("pretrain -1", opt("--pretrain", "-1"), "--pretrain must be >= 0"),
        ("clients 0", opt("--clients", "0"), "--clients must be >= 1"),
        ("seed -1", opt("--seed", "-1"), "--seed must be >= 0"),
        ("eval-views -1", opt("--eval-views", "-1"), "--eval-views must be >= 0"),
        ("server-lr 0", opt("--server-lr", "0"), "--server-lr must be"),
        ("server-lr nan", opt("--server-lr", "nan"), "--server-lr must be"),
        ("momentum 1", opt("--server-momentum", "1"), "--server-momentum must be"),
        ("momentum -0.1", opt("--server-momentum", "-0.1"), "--server-momentum must be"),
        ("fail-client -3", opt("--fail-client", "-3"), "--fail-client must be"),
        ("port 70000", opt("--superlink-port", "70000"), "--superlink-port must be"),
        ("preset", opt("--preset", "nope"), "nope"),
        ("dtype", opt("--transfer-dtype", "fp8"), "invalid choice"),
        ("missing input", lambda f, t: [str(t / "nope"), "--out", str(t / "run")], "no such"),
        ("clients 3 of 2", opt("--clients", "3"), "holds 2 shards but --clients is 3"),
        ("corrupt shard", damaged("flip"), "client_1.h5"),
        ("missing shard", damaged("missing"), "holds 1 shards"),
        ("gap in shards", damaged("renamed"), "client_0.h5 ... client_{K-1}.h5"),
        ("shard without train", damaged("no_train"), "client_1.h5: holds no train views"),
    ]


def _check(command: str, argv: list[str], message: str, tmp: Path) -> None:
    before = {p for p in tmp.rglob("*")}
    res = run_cli([command, *argv])
    assert res.one_line_error(command), res
    assert message in res.err.splitlines()[-1], res.err
    made = {p for p in tmp.rglob("*")} - before
    assert not [p for p in made if p.name != "run"], f"left behind: {sorted(made)}"


@pytest.mark.parametrize(("name", "argv", "message"), SPLIT, ids=[c[0] for c in SPLIT])
def test_split_catalogue(small_files, tmp_path: Path, name, argv, message) -> None:
    args = argv(small_files, tmp_path)
    _check("split", [*args, "-o", str(tmp_path / "out.h5")], message, tmp_path)


@pytest.mark.parametrize(("name", "argv", "message"), SHARD, ids=[c[0] for c in SHARD])
def test_shard_catalogue(small_files, tmp_path: Path, name, argv, message) -> None:
    args = argv(small_files, tmp_path)
    _check("shard", ["-o", str(tmp_path / "shards_out"), *args], message, tmp_path)


@pytest.mark.parametrize("index", range(22))
def test_federate_catalogue(small_files, shards: Path, tmp_path: Path, index: int) -> None:
    cases = federate_cases(shards)
    assert len(cases) == 22
    name, argv, message = cases[index]
    _check("federate", argv(small_files, tmp_path), message, tmp_path)


def test_federate_refuses_a_run_folder_made_from_other_shards(
    small_files: dict[str, Path], tmp_path: Path
) -> None:
    """Same paths, other contents (re-sharded with another seed): not resumed silently."""
    src = tmp_path / "shards"
    shard_dataset(small_files["dataset"], src, 2, "iid", seed=0)
    argv = [str(src), "--clients", "2", "--preset", "test", "--out", str(tmp_path / "run")]
    assert run_cli(["federate", *argv, "--deployment"]).code == 0
    shard_dataset(small_files["dataset"], src, 2, "iid", seed=5)
    res = run_cli(["federate", *argv, "--deployment"])
    assert res.one_line_error("federate"), res
    assert "other shard contents (client_0.h5, client_1.h5)" in res.err


# ----------------------------------------------------------------------------------------------
# Round 3: files and peers from elsewhere (issue 32). One row per case: command, the input it
# is given (built in a scratch folder), a fragment of its one error line. Every row must exit 1
# with that one line, no traceback, nothing executed (no MARKER) and nothing left behind.
# ----------------------------------------------------------------------------------------------


def _video(tmp: Path, name: str = "m.mp4") -> Path:
    """A file whose bytes say MP4 (the checks refuse it before decoding anything)."""
    (tmp / name).write_bytes(b"\0\0\0\x18ftypmp42" + bytes(64))
    return tmp / name


def _evil_checkpoint(tmp: Path) -> Path:
    import os

    import torch

    class Payload:
        def __reduce__(self):
            return (os.system, (f"touch {tmp / 'MARKER'}",))

    (tmp / "run").mkdir()
    torch.save({"version": 1, "field": Payload()}, tmp / "run" / "checkpoint.pt")
    return tmp / "run"


def _transforms(tmp: Path, file_paths: list[str]) -> Path:
    import json

    import cv2

    scene = tmp / "scene"
    scene.mkdir()
    cv2.imwrite(str(scene / "img.png"), np.full((12, 16, 3), 128, np.uint8))
    frames = [{"file_path": p, "transform_matrix": np.eye(4).tolist()} for p in file_paths]
    (scene / "transforms.json").write_text(json.dumps({"fl_x": 20.0, "frames": frames}))
    return scene


def _fifo_scene(tmp: Path) -> Path:
    import os

    scene = _transforms(tmp, ["img.png", "pipe.png"])
    os.mkfifo(scene / "pipe.png")
    return scene


def _bomb_folder(tmp: Path) -> Path:
    from tests.reliability.test_limits import bomb_png

    (tmp / "cap").mkdir()
    bomb_png(tmp / "cap" / "a.png")
    return tmp / "cap"


def _pipelines(tmp: Path, text: str) -> Path:
    (tmp / "p.yaml").write_text(text)
    return tmp / "p.yaml"


def _linked(files: dict[str, Path], tmp: Path) -> Path:
    import h5py

    path = tmp / "linked.h5"
    shutil.copy(files["dataset"], path)
    with h5py.File(path, "a") as f:
        f["extra/leak"] = h5py.ExternalLink("/etc/passwd", "/")
    return path


def _one_point(files: dict[str, Path], tmp: Path) -> Path:
    ds = open_dataset(files["dataset"])
    ds.poses[:, :3, 3] = ds.poses[0, :3, 3]
    return write_dataset(tmp / "one_point.h5", ds)


_SIM = "{command: simulate, params: {scene: corridor, frames: 3}}"
_TAG = "p:\n  stages:\n    s: {command: simulate, params: {scene: !!python/object/apply:os.system"
HOSTILE: list[tuple[str, str, Callable[[dict[str, Path], Path], list[str]], str]] = [
    ("render", "malicious checkpoint", lambda f, t: [str(_evil_checkpoint(t)), "--dataset",
     str(f["dataset"])], "refusing to load"),
    ("eval", "malicious checkpoint", lambda f, t: [str(_evil_checkpoint(t)), "--dataset",
     str(f["dataset"])], "refusing to load"),
    ("export-geometry", "malicious checkpoint", lambda f, t: [str(_evil_checkpoint(t)),
     "--dataset", str(f["dataset"])], "python -m dronecap.nerf.checkpoint --trust"),
    ("cost", "malicious checkpoint", lambda f, t: [str(_evil_checkpoint(t))], "refusing to load"),
    ("run", "stage ../../victim", lambda f, t: ["p", "--file", str(_pipelines(t, f"p:\n  stages:"
     f"\n    '../../victim': {_SIM}\n")), "--runs", str(t / "runs")], "stage name '../../victim'"),
    ("run", "pipeline ../x", lambda f, t: ["../x", "--file", str(_pipelines(t, f"'../x':\n  "
     f"stages:\n    s: {_SIM}\n")), "--runs", str(t / "runs")], "pipeline name '../x'"),
    ("run", "python tag", lambda f, t: ["p", "--file", str(_pipelines(t, _TAG + " ['touch "
     f"{t}/MARKER'], frames: 3}}}}\n")), "--runs", str(t / "runs")], "is not allowed"),
    ("ingest", "-o the input video", lambda f, t: [str(_video(t)), "-o", str(t / "m.mp4")],
     "is also an input of this command"),
    ("split", "-o an existing video", lambda f, t: [str(f["posed"]), "-o", str(_video(t))],
     "holds a video and this command writes an HDF5 file"),
    ("split", "-o the input", lambda f, t: [str(shutil.copy(f["posed"], t / "p.h5")), "-o",
     str(t / "p.h5")], "is also an input of this command"),
    ("ingest", "--size 6000", lambda f, t: [str(_video(t)), "-o", str(t / "f.h5"), "--size",
     "6000"], "is too large"),
    ("ingest", "image bomb", lambda f, t: [str(_bomb_folder(t)), "-o", str(t / "f.h5")],
     "30000x30000 (900 MP)"),
    ("import-transforms", "file_path ../x.png", lambda f, t: [str(_transforms(t, ["img.png",
     "../x.png"])), "-o", str(t / "o.h5")], "leaves the folder"),
    ("import-transforms", "absolute file_path", lambda f, t: [str(_transforms(t, ["img.png",
     "/etc/hostname"])), "-o", str(t / "o.h5")], "leaves the folder"),
    ("import-transforms", "FIFO as an image", lambda f, t: [str(_fifo_scene(t)), "-o",
     str(t / "o.h5")], "not a regular file"),
    ("import-transforms", "50 000 entries", lambda f, t: [str(_transforms(t, ["img.png"] *
     50_000)), "-o", str(t / "o.h5")], "lists 50000 frames"),
    ("split", "HDF5 external link", lambda f, t: [str(_linked(f, t)), "-o", str(t / "o.h5")],
     "extra/leak: an external link"),
    ("shard", "cameras at one point", lambda f, t: [str(_one_point(f, t)), "--scheme", "sector",
     "-o", str(t / "shards")], "distinct azimuths"),
]  # fmt: skip


@pytest.mark.parametrize(
    ("command", "name", "argv", "message"), HOSTILE, ids=[f"{c[0]}: {c[1]}" for c in HOSTILE]
)
def test_hostile_catalogue(small_files, tmp_path: Path, command, name, argv, message) -> None:
    args = argv(small_files, tmp_path)
    before = {p: p.stat().st_mtime_ns for p in tmp_path.rglob("*") if not p.is_fifo()}
    res = run_cli([command, *args])
    assert res.one_line_error(command), res
    assert res.code == 1 and message in res.err.splitlines()[-1], res.err
    assert not (tmp_path / "MARKER").exists()
    after = {p: p.stat().st_mtime_ns for p in tmp_path.rglob("*") if not p.is_fifo()}
    assert after == before, f"written: {sorted(set(after.items()) ^ set(before.items()))}"
