"""Geometry of a trained model: a mesh (marching cubes) and a coloured point cloud, as PLY.

1. **Density grid**: the field's density (per scene unit) sampled at the corners of a regular
   ``resolution^3`` grid spanning the scene AABB; samples in cells the occupancy grid marks
   empty count as zero (they hold no surface the renderer would draw).
2. **Surface level**: a density is read as "surface" when one grid step through it is at least
   ``opacity`` opaque: ``level = -ln(1 - opacity) / step`` (``step`` = the longest grid spacing),
   so the threshold follows the grid and the scene's units instead of a magic number.
3. **Mesh**: scikit-image's marching cubes at that level, vertices in scene units (the dataset's
   frame), normals pointing out of the dense region (towards falling density).
4. **Colours**: the field's colour at each vertex seen along its inward normal (as a camera in
   front of the surface would see it); gray models give gray colours.

Output (open3d's PLY writer, one folder written atomically): ``mesh.ply`` (vertices, normals,
colours, triangles) and ``points.ply`` (the mesh vertices as a point cloud with normals and
colours). A model with a far field (:mod:`nerf.far_field`: what its rays see past the box, the
walls and sky of a flight, the backdrop of an object) also gets it, since the mesh alone leaves
that out: ``far_field.json`` (kind, parameters and how they give a colour per direction) and
``far_field.png`` (the same as an equirectangular environment map, 8-bit, azimuth about the
scene's z axis across, +z at the top), in the mesh's frame.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from dronecap.errors import InputError

MESH = "mesh.ply"
POINTS = "points.ply"
FAR_JSON, FAR_PNG = "far_field.json", "far_field.png"
CHUNK = 1 << 16  # points per field evaluation


@dataclass
class Geometry:
    """A surface extracted from a model."""

    vertices: np.ndarray  # float64 [V, 3] scene units
    faces: np.ndarray  # int32 [F, 3]
    normals: np.ndarray  # float64 [V, 3] unit, outwards
    colors: np.ndarray  # float64 [V, 3] in [0, 1]
    level: float  # density threshold (per scene unit)
    far: dict | None = None  # nerf.far_field.far_field_record of the model's far field
    far_map: np.ndarray | None = None  # float32 [rows, 2 rows, C] its environment map


def density_grid(trainer, resolution: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Density [R, R, R] float32 at the corners of a grid over the AABB, the grid origin [3]
    and spacing [3] (scene units)."""
    import torch

    from dronecap.nerf import occupancy

    aabb = trainer.aabb.detach().cpu().numpy().astype(np.float64)
    axes = [np.linspace(lo, hi, resolution) for lo, hi in aabb.T]
    pts = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    out = np.empty(len(pts), np.float32)
    with torch.no_grad():
        for s in range(0, len(pts), CHUNK):
            x = torch.as_tensor(pts[s : s + CHUNK], dtype=torch.float32, device=trainer.device)
            sigma = trainer.field.density(x)
            sigma = torch.where(occupancy.occupied_at(trainer.grid, x, trainer.aabb), sigma, 0)
            out[s : s + CHUNK] = sigma.float().cpu().numpy()
    spacing = (aabb[1] - aabb[0]) / (resolution - 1)
    return out.reshape((resolution,) * 3), aabb[0], spacing


def surface_level(spacing: np.ndarray, opacity: float) -> float:
    """Density at which one grid step is ``opacity`` opaque (see the module docstring)."""
    return float(-np.log1p(-opacity) / float(np.max(spacing)))


def extract(trainer, resolution: int = 128, opacity: float = 0.5) -> Geometry:
    """Mesh and colours of a trained model (see the module docstring).

    Raises:
        InputError: no surface at that level (the model is empty or everywhere dense).
    """
    import torch
    from skimage.measure import marching_cubes

    sigma, origin, spacing = density_grid(trainer, resolution)
    level = surface_level(spacing, opacity)
    if not sigma.min() < level < sigma.max():
        raise InputError(
            f"no surface: density spans {sigma.min():.3g}..{sigma.max():.3g} per unit, the "
            f"surface level is {level:.3g} (--opacity {opacity}); train longer or lower --opacity"
        )
    verts, faces, normals, _ = marching_cubes(sigma, level=level, spacing=tuple(spacing))
    verts = verts.astype(np.float64) + origin
    # skimage's normals point down the gradient: from the dense side out (tested on a cube)
    normals = normals.astype(np.float64)
    normals /= np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-12)
    cols = []
    with torch.no_grad():
        for s in range(0, len(verts), CHUNK):
            x = torch.as_tensor(verts[s : s + CHUNK], dtype=torch.float32, device=trainer.device)
            d = torch.as_tensor(-normals[s : s + CHUNK], dtype=torch.float32, device=trainer.device)
            cols.append(trainer.field(x, d)[0].float().cpu().numpy())
    rgb = np.concatenate(cols) if cols else np.zeros((0, 1))
    if rgb.shape[1] == 1:
        rgb = np.repeat(rgb, 3, axis=1)
    geo = Geometry(verts, faces.astype(np.int32), normals, np.clip(rgb, 0, 1), level)
    far = trainer.field.far
    if far is not None:
        from dronecap.nerf.far_field import environment_map, far_field_record

        geo.far, geo.far_map = far_field_record(far), environment_map(far)
    return geo


def write_geometry(geo: Geometry, out_dir: str | Path) -> Path:
    """Write ``out_dir`` (atomically, replacing it) with ``mesh.ply`` and ``points.ply``."""
    import open3d as o3d

    from dronecap.files import atomic_output

    out_dir = Path(out_dir)
    vec3 = o3d.utility.Vector3dVector
    mesh = o3d.geometry.TriangleMesh(vec3(geo.vertices), o3d.utility.Vector3iVector(geo.faces))
    mesh.vertex_normals = vec3(geo.normals)
    mesh.vertex_colors = vec3(geo.colors)
    cloud = o3d.geometry.PointCloud(vec3(geo.vertices))
    cloud.normals = vec3(geo.normals)
    cloud.colors = vec3(geo.colors)
    with atomic_output(out_dir) as tmp:
        tmp.mkdir()
        if not o3d.io.write_triangle_mesh(str(tmp / MESH), mesh):
            raise InputError("open3d could not write the mesh", out_dir / MESH)
        if not o3d.io.write_point_cloud(str(tmp / POINTS), cloud):
            raise InputError("open3d could not write the point cloud", out_dir / POINTS)
        if geo.far is not None:
            _write_far_field(geo.far, geo.far_map, tmp)
    return out_dir


def _write_far_field(record: dict, env: np.ndarray, folder: Path) -> None:
    """``far_field.json`` (``record``) and ``far_field.png`` (``env`` [rows, cols, C] in [0,
    1], 8-bit gray or RGB) in ``folder``."""
    import json

    import cv2

    (folder / FAR_JSON).write_text(json.dumps(record, indent=1))
    img = np.round(np.clip(env, 0, 1) * 255).astype(np.uint8)
    cv2.imwrite(str(folder / FAR_PNG), img[..., ::-1] if img.shape[-1] == 3 else img[..., 0])
