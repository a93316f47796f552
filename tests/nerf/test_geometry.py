"""Geometry export of a model: marching cubes at the opacity level, outward normals, colours
seen from outside, PLY files; the command end to end on a trained cube run."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from dronecap.cli import main
from dronecap.nerf.config import preset
from dronecap.nerf.geometry import extract, surface_level, write_geometry
from dronecap.nerf.trainer import Trainer

from .conftest import FACE_COLOURS, cube_dataset

o3d = pytest.importorskip(
    "open3d", reason="geometry export writes PLY with open3d (the [sim] extra)"
)


def face_of(x: torch.Tensor) -> torch.Tensor:
    """Index into FACE_COLOURS of the cube face nearest each point (as the cube renderer)."""
    axis = x.abs().argmax(1)
    return axis * 2 + (x.gather(1, axis[:, None])[:, 0] > 0).long()


@pytest.fixture(scope="module")
def cube_model() -> Trainer:
    """A real model whose field is fitted straight to the cube [-0.5, 0.5]^3: density 40 inside,
    0 outside, each face's colour near it (seconds, unlike photometric training)."""
    torch.manual_seed(0)
    tr = Trainer(preset("test"), cube_dataset(n=8, size=16))
    opt = torch.optim.Adam(tr.field.parameters(), lr=1e-2)
    g = torch.Generator().manual_seed(0)
    colours = torch.as_tensor(FACE_COLOURS, dtype=torch.float32)
    for _ in range(300):
        x = torch.rand(8192, 3, generator=g) * 2 - 1
        target = torch.where(x.abs().max(1).values < 0.5, 40.0, 0.0)
        d = torch.nn.functional.normalize(torch.randn(8192, 3, generator=g), dim=1)
        rgb, sigma = tr.field(x, d)
        near = (x.abs().max(1).values - 0.5).abs() < 0.1
        loss = ((torch.log1p(sigma) - torch.log1p(target)) ** 2).mean()
        loss = loss + ((rgb - colours[face_of(x)]) ** 2)[near].mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
    return tr


def test_surface_level_is_the_opacity_of_one_grid_step() -> None:
    # one step of 0.1 through density 10 * ln 2 is 50 % opaque
    assert surface_level(np.array([0.05, 0.1, 0.08]), 0.5) == pytest.approx(10 * np.log(2))


def test_mesh_lies_on_the_cube_with_outward_normals_and_face_colours(cube_model, tmp_path):
    geo = extract(cube_model, resolution=48, opacity=0.5)
    v = geo.vertices
    spacing = 2 / 47
    dist = np.abs(np.abs(v).max(1) - 0.5)  # distance to the cube's surface (outside the edges)
    assert len(v) > 1000 and np.median(dist) < 0.5 * spacing
    assert np.percentile(dist, 95) < 2 * spacing  # a few floaters where the fit is loose
    assert (np.sum(geo.normals * v, 1) > 0).mean() > 0.98  # outward: away from the centre
    np.testing.assert_allclose(np.linalg.norm(geo.normals, axis=1), 1, atol=1e-6)
    # each face's vertices (away from the edges) carry, of the six colours, that face's
    faces = face_of(torch.as_tensor(v)).numpy()
    centre = (np.abs(v).max(1) - np.sort(np.abs(v), 1)[:, 1]) > 0.1
    for f in range(6):
        median = np.median(geo.colors[(faces == f) & centre], 0)
        assert np.argmin(np.linalg.norm(FACE_COLOURS - median, axis=1)) == f
    out = write_geometry(geo, tmp_path / "g")
    mesh = o3d.io.read_triangle_mesh(str(out / "mesh.ply"))
    np.testing.assert_allclose(np.asarray(mesh.vertices), v, atol=1e-6)
    assert len(mesh.triangles) == len(geo.faces)
    np.testing.assert_allclose(np.asarray(mesh.vertex_colors), geo.colors, atol=1 / 255)
    cloud = o3d.io.read_point_cloud(str(out / "points.ply"))
    assert len(cloud.points) == len(v) and cloud.has_colors() and cloud.has_normals()


def test_an_empty_model_has_no_surface(cube_model) -> None:
    from dronecap.errors import InputError

    with pytest.raises(InputError, match="no surface"):
        extract(cube_model, resolution=16, opacity=0.999999)


def test_command_on_a_trained_cube_run(cube_h5, tmp_path, capsys) -> None:
    """60 steps leave a faint model: a low --opacity still finds its surface."""
    run = tmp_path / "run"
    train = ["train", str(cube_h5), "--preset", "test", "--steps", "60", "--out", str(run)]
    assert main([*train, "--no-progress", "--threads", "1", "--no-eval"]) == 0
    assert main(["export-geometry", str(run), "--resolution", "24", "--opacity", "0.01"]) == 0
    assert "mesh.ply" in capsys.readouterr().out
    v = np.asarray(o3d.io.read_triangle_mesh(str(run / "geometry/mesh.ply")).vertices)
    assert len(v) > 0 and (np.abs(v) <= 1 + 1e-6).all()  # inside the cube dataset's AABB
    for bad, message in (
        (["--opacity", "1"], "--opacity"),
        (["--resolution", "4"], "--resolution"),
    ):
        assert main(["export-geometry", str(run), "-o", str(tmp_path / "x"), *bad]) == 1
        assert message in capsys.readouterr().err
    assert main(["export-geometry", str(tmp_path)]) == 1
    assert "not a training run" in capsys.readouterr().err
    assert not (tmp_path / "x").exists() and not (tmp_path / "geometry").exists()
