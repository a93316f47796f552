"""Exported points carry the frames' colours when the points have none (an SfM model without
colour), and the export says how nerfstudio keeps the exported frame and box."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pycolmap

from dronecap.datasets.blender import import_blender
from dronecap.datasets.export import export_transforms, nerfstudio_args
from dronecap.datasets.export_colmap import POINTS_RGB, POINTS_XYZ
from dronecap.datasets.format import open_dataset, write_dataset
from dronecap.datasets.import_transforms import import_transforms

from .conftest import BOX, BOX_RGB


def test_black_points_take_the_frames_colour(box_scene: Path, tmp_path: Path) -> None:
    ds = open_dataset(import_blender(box_scene, tmp_path / "box.h5", progress=False))
    top = [(BOX[0, 0] + BOX[1, 0]) / 2, (BOX[0, 1] + BOX[1, 1]) / 2, BOX[1, 2]]
    side = [BOX[1, 0], 0.0, (BOX[0, 2] + BOX[1, 2]) / 2]
    far = [0.0, 0.0, 3.0 * BOX[1, 2] + 1.0]  # above the box: the views see it on the background
    xyz = np.array([top, side, far])
    extra = {**ds.extra, POINTS_XYZ: xyz, POINTS_RGB: np.zeros((3, 3), np.uint8)}
    write_dataset(tmp_path / "pts.h5", dataclasses.replace(ds, extra=extra))
    out = export_transforms(tmp_path / "pts.h5", tmp_path / "x").out_dir
    rec = pycolmap.Reconstruction()
    rec.import_PLY(str(out / "sparse_pc.ply"))
    got = {tuple(np.round(p.xyz, 5)): tuple(p.color) for p in rec.points3D.values()}
    assert got[tuple(np.round(xyz[0], 5))] == BOX_RGB
    assert got[tuple(np.round(xyz[1], 5))] == BOX_RGB
    assert got[tuple(np.round(xyz[2], 5))] == (0, 0, 0)  # the background's straight colour
    text = pycolmap.Reconstruction(str(out / "colmap" / "text"))
    assert sorted(tuple(p.color) for p in text.points3D.values()) == sorted(got.values())


def test_export_names_nerfstudios_options_that_keep_the_frame(
    lego_h5: Path, tmp_path: Path
) -> None:
    ds = open_dataset(lego_h5)
    res = export_transforms(lego_h5, tmp_path / "x")
    meta = json.loads((res.out_dir / "transforms.json").read_text())
    args = meta["dronecap_nerfstudio_args"].split()
    for opt, val in (("--orientation-method", "none"), ("--center-method", "none"),
                     ("--auto-scale-poses", "False")):  # fmt: skip
        assert args[args.index(opt) + 1] == val
    s = float(args[args.index("--scene-scale") + 1])
    assert (np.abs(ds.aabb) <= s).all() and s < np.abs(ds.aabb).max() + 1e-3
    assert any("ns-train nerfacto" in n for n in res.notes)
    assert nerfstudio_args(None).endswith("False")
    # and the export imports back with its box and poses exactly
    back = open_dataset(import_transforms(res.out_dir, tmp_path / "b.h5", progress=False))
    np.testing.assert_array_equal(back.aabb, ds.aabb)
    np.testing.assert_array_equal(back.poses, ds.poses)
