"""Simulated scenes: triangle geometry for open3d ray casting, gray materials and lights.

World axes: x along the corridor (or east), y to the left, z up; metres. Two scenes:

- ``corridor``: a 6.5 m corridor 1.6 m wide and 2.4 m high (brick wall on the left, plaster
  with posters and doors on the right, tiled floor, panelled ceiling, a poster wall at the far
  end, x = 5.5 m) with two traffic cones on the floor ahead of the drone, as in the paper's
  in-field dataset.
- ``orbit``: a room with a pedestal, two cones, a ball and a crate at its centre, for an orbit.

A material maps hit points ([3, M] arrays) to albedo in [0, 1]; the renderer multiplies albedo
by the diffuse irradiance of a few point lights plus an ambient term.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from dronecap.simulator.textures import MipTexture, add_posters, camo, tiles

TEXEL = 0.005  # metres per texel of the wall/floor textures
Albedo = Callable[[np.ndarray, np.ndarray, np.ndarray], np.ndarray]


class PlanarMaterial:
    """Texture projected along the dominant axis of the surface normal (walls, floors, boxes).

    For a surface facing +-z, (u, v) = (x, y) - origin; facing +-x, (u, v) = (y, top - z);
    facing +-y, (u, v) = (x, top - z), so texture rows run downwards on walls.
    """

    def __init__(self, texture: MipTexture, origin: tuple[float, float, float]) -> None:
        self.texture = texture
        self.origin = np.asarray(origin, float)

    def __call__(
        self, points: np.ndarray, normals: np.ndarray, footprint: np.ndarray
    ) -> np.ndarray:
        """Albedo float32 [M] of hits ``points`` [3, M] with ``normals`` [3, M] (metres)."""
        q = points - self.origin[:, None].astype(points.dtype)
        a = np.abs(normals)
        faces_x = (a[0] >= a[1]) & (a[0] >= a[2])
        faces_z = ~faces_x & (a[2] >= a[1])
        u = np.where(faces_x, q[1], q[0])
        v = np.where(faces_z, q[1], -q[2])
        return self.texture.sample(u, v, footprint)


class ConeMaterial:
    """Traffic cone seen in gray: orange (~0.5) with a white band (0.92) and a dark base."""

    def __init__(self, base_z: float, height: float) -> None:
        self.base_z, self.height = base_z, height

    def __call__(
        self, points: np.ndarray, normals: np.ndarray, footprint: np.ndarray
    ) -> np.ndarray:
        """Albedo float32 [M] from the height of each hit (``points`` [3, M]) above the base."""
        h = (points[2] - self.base_z) / self.height
        out = np.full(points.shape[1], 0.5, np.float32)
        out[(h > 0.35) & (h < 0.55)] = 0.92
        out[h < 0.04] = 0.12
        return out


@dataclass
class Light:
    """Point light: position (m) and intensity (irradiance 1 at 1 m, facing it)."""

    position: tuple[float, float, float]
    intensity: float


@dataclass
class Scene:
    """Geometry (one open3d mesh per material) plus lights and a JSON-able description."""

    name: str
    meshes: list[tuple[np.ndarray, np.ndarray]]  # (vertices float32 [V, 3], triangles [T, 3])
    materials: list[Albedo]  # material of each mesh (index = open3d geometry id)
    lights: list[Light]
    ambient: float
    description: dict[str, object] = field(default_factory=dict)
    _raycaster: object | None = None

    @property
    def raycaster(self) -> object:
        """The open3d ``RaycastingScene`` holding every mesh (built on first use)."""
        if self._raycaster is None:
            import open3d as o3d

            rc = o3d.t.geometry.RaycastingScene()
            for v, t in self.meshes:
                mesh = o3d.t.geometry.TriangleMesh()
                mesh.vertex.positions = o3d.core.Tensor(np.asarray(v, np.float32))
                mesh.triangle.indices = o3d.core.Tensor(np.asarray(t, np.int32))
                rc.add_triangles(mesh)
            self._raycaster = rc
        return self._raycaster


def box_mesh(lo: tuple[float, ...], hi: tuple[float, ...]) -> tuple[np.ndarray, np.ndarray]:
    """Axis-aligned box from corner ``lo`` to ``hi`` (m): vertices [8, 3], triangles [12, 3]."""
    x0, y0, z0 = lo
    x1, y1, z1 = hi
    v = np.array(
        [[x, y, z] for z in (z0, z1) for y in (y0, y1) for x in (x0, x1)], np.float32
    )  # index = 4 * iz + 2 * iy + ix
    quads = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]
    t = np.array([tri for a, b, c, d in quads for tri in ((a, b, c), (a, c, d))], np.int32)
    return v, t


def quad_mesh(corners: list[tuple[float, float, float]]) -> tuple[np.ndarray, np.ndarray]:
    """Planar quad from 4 corners in order: vertices [4, 3], triangles [2, 3]."""
    return np.array(corners, np.float32), np.array([[0, 1, 2], [0, 2, 3]], np.int32)


def cone_mesh(
    centre: tuple[float, float], radius: float, height: float, segments: int = 48
) -> tuple[np.ndarray, np.ndarray]:
    """Upright cone standing on z = 0 at ``centre`` (x, y): vertices and triangles."""
    a = np.linspace(0, 2 * np.pi, segments, endpoint=False)
    ring = np.stack([centre[0] + radius * np.cos(a), centre[1] + radius * np.sin(a), 0 * a], 1)
    v = np.vstack([ring, [[centre[0], centre[1], height], [centre[0], centre[1], 0.0]]])
    i = np.arange(segments)
    j = (i + 1) % segments
    side = np.stack([i, j, np.full(segments, segments)], 1)
    bottom = np.stack([j, i, np.full(segments, segments + 1)], 1)
    return v.astype(np.float32), np.vstack([side, bottom]).astype(np.int32)


def _wall_texture(rng: np.random.Generator, w: int, h: int, kind: str) -> np.ndarray:
    """Texture [h, w] texels for a wall ``kind``: 'brick', 'plaster' or 'posters'."""
    fine = camo(rng, (h, w), (40.0, 12.0, 5.0), levels=6)
    if kind == "brick":
        # Stains at large scale make each stretch of the (repetitive) bricks unique.
        stains = camo(rng, (h, w), (150.0, 50.0, 15.0), levels=6)
        base = tiles(rng, (h, w), (16, 48), 2, stagger=True) * (0.45 + 0.55 * stains)
        base *= 0.85 + 0.2 * fine
    else:
        base = 0.45 + 0.35 * camo(rng, (h, w), (90.0, 30.0, 10.0), levels=5)
    if kind == "plaster":  # doors: tall dark frames with a lighter panel
        for x0 in rng.choice(np.arange(60, w - 220, 20), size=max(1, w // 500), replace=False):
            base[h - 420 :, x0 : x0 + 180] = 0.1
            base[h - 408 :, x0 + 10 : x0 + 170] = 0.55 + 0.2 * fine[h - 408 :, x0 + 10 : x0 + 170]
    base = add_posters(rng, base, count=max(2, w // 90), size=(50, 160), rows=(40, h - 220))
    base[h - 20 :] = 0.2 + 0.1 * fine[h - 20 :]  # baseboard
    return np.clip(base, 0, 1)


def corridor(seed: int = 0) -> Scene:
    """The corridor scene (see module docstring); textures depend on ``seed``."""
    rng = np.random.default_rng([seed, 1])
    x0, x1, hw, top = -1.0, 5.5, 0.8, 2.4
    length, width, height = x1 - x0, 2 * hw, top
    px = int(length / TEXEL)
    pw, ph = int(width / TEXEL), int(height / TEXEL)
    stains = camo(rng, (pw, px), (120.0, 40.0, 10.0), levels=6)
    floor_tex = tiles(rng, (pw, px), (60, 60), 2) * (0.5 + 0.55 * stains)
    # Ceiling panels and lamps repeat along the flight direction, where a repeated pattern can
    # be matched to the wrong copy consistently with a wrong motion: stains and lamps of random
    # size and pattern make every stretch unique.
    stains = camo(rng, (pw, px), (100.0, 30.0, 10.0), levels=5)
    ceiling_tex = tiles(rng, (pw, px), (120, 120), 4) * (0.25 + 0.45 * stains) + 0.1
    for xc in np.arange(100, px - 200, 300) + rng.integers(-60, 60, len(range(100, px - 200, 300))):
        half, length = int(rng.integers(15, 35)), int(rng.integers(70, 180))
        lamp = ceiling_tex[pw // 2 - half : pw // 2 + half, xc : xc + length]
        lamp[:] = 0.55 + 0.3 * camo(rng, lamp.shape, (20.0, 6.0), levels=3)
    walls = {
        "left": (
            _wall_texture(rng, px, ph, "brick"),
            [(x0, hw, 0), (x1, hw, 0), (x1, hw, top), (x0, hw, top)],
        ),
        "right": (
            _wall_texture(rng, px, ph, "plaster"),
            [(x0, -hw, 0), (x0, -hw, top), (x1, -hw, top), (x1, -hw, 0)],
        ),
        "end": (
            _wall_texture(rng, pw, ph, "posters"),
            [(x1, -hw, 0), (x1, -hw, top), (x1, hw, top), (x1, hw, 0)],
        ),
        "back": (
            _wall_texture(rng, pw, ph, "posters"),
            [(x0, -hw, 0), (x0, hw, 0), (x0, hw, top), (x0, -hw, top)],
        ),
        "floor": (floor_tex, [(x0, -hw, 0), (x1, -hw, 0), (x1, hw, 0), (x0, hw, 0)]),
        "ceiling": (ceiling_tex, [(x0, -hw, top), (x0, hw, top), (x1, hw, top), (x1, -hw, top)]),
    }
    meshes, materials = [], []
    for tex, corners in walls.values():
        meshes.append(quad_mesh(corners))
        materials.append(PlanarMaterial(MipTexture(tex, TEXEL), (x0, -hw, top)))
    cones = [{"position": [3.6, 0.3, 0.0]}, {"position": [4.5, -0.35, 0.0]}]
    for c in cones:
        c.update(radius=0.14, height=0.45)
        meshes.append(cone_mesh(tuple(c["position"][:2]), c["radius"], c["height"]))
        materials.append(ConeMaterial(0.0, c["height"]))
    lights = [Light((x, 0.0, top - 0.1), 1.0) for x in (-0.5, 1.0, 2.5, 4.0, 5.2)]
    description = {
        "name": "corridor",
        "seed": seed,
        "axes": "world x along the corridor, y left, z up; metres",
        "bounds": [[x0, -hw, 0.0], [x1, hw, top]],
        "floor_z": 0.0,
        "cones": cones,
        "walls": list(walls),
    }
    return Scene("corridor", meshes, materials, lights, ambient=0.35, description=description)


def orbit(seed: int = 0) -> Scene:
    """A 6 m room with objects at its centre (pedestal, two cones, a ball, a crate)."""
    rng = np.random.default_rng([seed, 2])
    half, top = 3.0, 2.5
    n, ph = int(2 * half / TEXEL), int(top / TEXEL)
    meshes, materials = [], []
    floor = tiles(rng, (n, n), (80, 80), 3) * (0.75 + 0.3 * camo(rng, (n, n), (30.0, 9.0)))
    meshes.append(
        quad_mesh([(-half, -half, 0), (half, -half, 0), (half, half, 0), (-half, half, 0)])
    )
    materials.append(PlanarMaterial(MipTexture(floor, TEXEL), (-half, -half, top)))
    corners = [(-half, -half), (half, -half), (half, half), (-half, half)]
    for k in range(4):
        (ax, ay), (bx, by) = corners[k], corners[(k + 1) % 4]
        meshes.append(quad_mesh([(ax, ay, 0), (ax, ay, top), (bx, by, top), (bx, by, 0)]))
        tex = _wall_texture(rng, n, ph, "brick" if k % 2 else "plaster")
        materials.append(PlanarMaterial(MipTexture(tex, TEXEL), (-half, -half, top)))
    objects = camo(rng, (400, 400), (60.0, 20.0, 6.0), levels=6)
    pedestal = box_mesh((-0.35, -0.35, 0.0), (0.35, 0.35, 0.3))
    crate = box_mesh((0.05, -0.25, 0.3), (0.3, 0.0, 0.55))
    for mesh in (pedestal, crate):
        meshes.append(mesh)
        materials.append(PlanarMaterial(MipTexture(objects, 0.002), (-0.5, -0.5, 1.0)))
    import open3d as o3d

    ball = o3d.geometry.TriangleMesh.create_sphere(0.12, resolution=24)
    ball.translate((-0.15, 0.15, 0.42))
    meshes.append((np.asarray(ball.vertices, np.float32), np.asarray(ball.triangles, np.int32)))
    materials.append(PlanarMaterial(MipTexture(objects, 0.0015), (-0.3, -0.3, 1.0)))
    cones = [{"position": [0.7, 0.5, 0.0]}, {"position": [-0.6, -0.7, 0.0]}]
    for c in cones:
        c.update(radius=0.12, height=0.4)
        meshes.append(cone_mesh(tuple(c["position"][:2]), c["radius"], c["height"]))
        materials.append(ConeMaterial(0.0, c["height"]))
    lights = [Light((x, y, top - 0.1), 2.5) for x in (-1.5, 1.5) for y in (-1.5, 1.5)]
    description = {
        "name": "orbit",
        "seed": seed,
        "axes": "world x east, y north, z up; metres",
        "bounds": [[-half, -half, 0.0], [half, half, top]],
        "floor_z": 0.0,
        "cones": cones,
        "target": [0.0, 0.0, 0.35],
    }
    return Scene("orbit", meshes, materials, lights, ambient=0.3, description=description)


SCENES: dict[str, Callable[[int], Scene]] = {"corridor": corridor, "orbit": orbit}
