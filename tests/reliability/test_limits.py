"""Imported files stay in their folder and inside the machine's means: path containment, FIFOs,
frame counts, image bombs and HDF5 links, each refused in one line before the work starts.

The memory cases run the CLI in a child under a 6 GB address-space limit (``ulimit -v``), as a
user on a small machine would: a clean one-line error, never a MemoryError or a kill.
"""

from __future__ import annotations

import json
import os
import resource
import shutil
import struct
import subprocess
import sys
import zlib
from pathlib import Path

import cv2
import h5py
import numpy as np
import pytest

from tests.reliability.conftest import run_cli

SIX_GB = 6_000_000 * 1024  # ulimit -v 6000000 (KiB)


def bomb_png(path: Path, width: int = 30000, height: int = 30000) -> Path:
    """A PNG whose header says ``width`` x ``height`` RGB (its pixel data is a stub: only a
    reader that trusts the header before decoding is exercised)."""

    def chunk(kind: bytes, data: bytes) -> bytes:
        crc = zlib.crc32(kind + data)
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", crc)

    ihdr = struct.pack(">IIBBBBB", width, height, 8, 2, 0, 0, 0)
    body = chunk(b"IHDR", ihdr) + chunk(b"IDAT", zlib.compress(b"\0" * 1000)) + chunk(b"IEND", b"")
    path.write_bytes(b"\x89PNG\r\n\x1a\n" + body)
    return path


def limited(argv: list[str], cwd: Path, env: dict[str, str] | None = None):
    """``dronecap ARGV`` in a child process under a 6 GB address-space limit."""

    def limit() -> None:
        resource.setrlimit(resource.RLIMIT_AS, (SIX_GB, SIX_GB))

    return subprocess.run(
        [sys.executable, "-m", "dronecap.cli", "-q", *argv],
        cwd=cwd,
        capture_output=True,
        text=True,
        timeout=300,
        preexec_fn=limit,
        env={**os.environ, "DRONECAP_PROGRESS": "off", **(env or {})},
    )


def _scene(root: Path, file_paths: list[str]) -> Path:
    """A transforms.json folder with one small image ``img.png`` and frames naming
    ``file_paths``."""
    root.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(root / "img.png"), np.full((12, 16, 3), 128, np.uint8))
    frames = [{"file_path": fp, "transform_matrix": np.eye(4).tolist()} for fp in file_paths]
    meta = {"fl_x": 20.0, "aabb": [[-0.5] * 3, [0.5] * 3], "frames": frames}
    (root / "transforms.json").write_text(json.dumps(meta))
    return root


def _outside_cases(tmp: Path) -> dict[str, str]:
    outside = tmp / "x.png"
    cv2.imwrite(str(outside), np.zeros((12, 16, 3), np.uint8))
    link_dir = tmp / "scene_link"
    link_dir.mkdir()
    (link_dir / "leak.png").symlink_to(outside)
    return {"dotdot": "../x.png", "absolute": str(outside), "link": "leak.png"}


@pytest.mark.parametrize("case", ["dotdot", "absolute", "link"])
def test_import_paths_leaving_the_folder(tmp_path: Path, case: str) -> None:
    fp = _outside_cases(tmp_path)[case]
    scene = _scene(
        tmp_path / ("scene_link" if case == "link" else "scene"), ["img.png", "img.png", fp]
    )
    out = tmp_path / "out.h5"
    res = run_cli(["import-transforms", str(scene), "-o", str(out)])
    assert res.one_line_error("import-transforms"), res
    assert "leaves the folder" in res.err and "--allow-outside" in res.err, res.err
    assert not out.exists()
    res = run_cli(["import-transforms", str(scene), "-o", str(out), "--allow-outside"])
    assert res.code == 0, res
    assert out.exists()


def test_import_fifo_named_as_an_image(tmp_path: Path) -> None:
    scene = _scene(tmp_path / "scene", ["img.png", "pipe.png"])
    os.mkfifo(scene / "pipe.png")
    res = run_cli(["import-transforms", str(scene), "-o", str(tmp_path / "o.h5")], timeout_s=30)
    assert res.one_line_error("import-transforms"), res
    assert "not a regular file" in res.err


def test_fifo_in_a_colmap_or_blender_path_is_refused(tmp_path: Path) -> None:
    from dronecap.datasets.safe_paths import inside_folder
    from dronecap.errors import InputError

    os.mkfifo(tmp_path / "f.png")
    with pytest.raises(InputError, match="not a regular file"):
        inside_folder(tmp_path, tmp_path / "f.png")


def test_transforms_with_50000_entries_under_6_gb(tmp_path: Path) -> None:
    scene = _scene(tmp_path / "scene", ["img.png"] * 50_000)
    p = limited(["import-transforms", str(scene), "-o", str(tmp_path / "o.h5")], tmp_path)
    lines = p.stderr.strip().splitlines()
    assert p.returncode == 1 and len(lines) == 1, p.stderr
    assert "lists 50000 frames, more than the limit" in lines[0]
    assert "DRONECAP_MAX_FRAMES" in lines[0]


def test_import_memory_estimated_before_decoding_under_6_gb(tmp_path: Path) -> None:
    """Under the frame limit but far beyond memory at the size asked: refused naming --size."""
    scene = _scene(tmp_path / "scene", ["img.png"] * 15_000)
    argv = ["import-transforms", str(scene), "-o", str(tmp_path / "o.h5"), "--size", "1024"]
    p = limited(argv, tmp_path)
    lines = p.stderr.strip().splitlines()
    assert p.returncode == 1 and len(lines) == 1, p.stderr
    assert "15000 images would need about" in lines[0] and "lower --size" in lines[0]


def test_image_bomb_in_a_capture_folder_under_6_gb(tmp_path: Path) -> None:
    (tmp_path / "cap").mkdir()
    for i in range(3):
        bomb_png(tmp_path / "cap" / f"img{i}.png")
    p = limited(["ingest", "cap", "-o", "f.h5"], tmp_path)
    lines = p.stderr.strip().splitlines()
    assert p.returncode == 1 and len(lines) == 1, p.stderr
    assert "30000x30000 (900 MP), more than the 64 MP" in lines[0]
    assert "DRONECAP_MAX_PIXELS" in lines[0]
    assert sorted(q.name for q in tmp_path.iterdir()) == ["cap"]
    # raised past the pixel limit, the memory estimate still refuses it before decoding
    p = limited(["ingest", "cap", "-o", "f.h5"], tmp_path, {"DRONECAP_MAX_PIXELS": "1000000000"})
    assert p.returncode == 1 and "decoding this frame would need about" in p.stderr, p.stderr


def test_image_bomb_among_imported_images(tmp_path: Path) -> None:
    scene = _scene(tmp_path / "scene", ["img.png", "bomb.png"])
    bomb_png(scene / "bomb.png")
    res = run_cli(["import-transforms", str(scene), "-o", str(tmp_path / "o.h5")])
    assert res.one_line_error("import-transforms"), res
    assert "bomb.png: is 30000x30000" in res.err


def test_ingest_size_has_an_upper_bound(tmp_path: Path) -> None:
    (tmp_path / "cap").mkdir()
    cv2.imwrite(str(tmp_path / "cap" / "a.png"), np.zeros((12, 16), np.uint8))
    res = run_cli(["ingest", str(tmp_path / "cap"), "-o", str(tmp_path / "f.h5"), "--size", "6000"])
    assert res.one_line_error("ingest"), res
    assert "--size" in res.err and "too large" in res.err


@pytest.mark.parametrize("kind", ["external", "virtual"])
def test_hdf5_links_out_of_the_file_are_refused(small_files, tmp_path: Path, kind: str) -> None:
    target = tmp_path / "secret.h5"
    with h5py.File(target, "w") as g:
        g["data"] = np.arange(12.0)
    path = tmp_path / "linked.h5"
    shutil.copy(small_files["dataset"], path)
    with h5py.File(path, "a") as f:
        if kind == "external":
            f["extra/leak"] = h5py.ExternalLink(str(target), "/data")
        else:
            layout = h5py.VirtualLayout(shape=(12,), dtype="f8")
            layout[:] = h5py.VirtualSource(str(target), "data", shape=(12,))
            f.create_virtual_dataset("extra/leak", layout)
    res = run_cli(["split", str(path), "-o", str(tmp_path / "out.h5")])
    assert res.one_line_error("split"), res
    assert "extra/leak" in res.err and "refused" in res.err, res.err
    assert not (tmp_path / "out.h5").exists()
