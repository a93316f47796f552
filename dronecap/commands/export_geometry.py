"""`dronecap export-geometry`: a trained run -> mesh.ply + points.ply (marching cubes), and the
far field (far_field.json + .png) when the model has one."""

from __future__ import annotations

from dataclasses import dataclass

from dronecap.settings import TorchSettings, output_setting, setting


@dataclass(kw_only=True)
class Settings(TorchSettings):
    """Options of ``dronecap export-geometry``."""

    run_dir: str = setting(
        positional=True, help="training run folder (holds checkpoint.pt and run.json)"
    )
    output: str | None = output_setting("folder to write", "RUN_DIR/geometry")
    dataset: str | None = setting(None, help="dataset of the run (default: the one run.json names)")
    resolution: int = setting(
        128, minimum=8, maximum=1024, help="density grid points per axis over the AABB"
    )
    opacity: float = setting(
        0.5, help="surface level: the opacity one grid step must reach (0 < opacity < 1)"
    )


def run(s: Settings) -> int:
    """Extract, write, and say what."""
    from pathlib import Path

    from dronecap.cpu import check_threads, use_torch_threads
    from dronecap.errors import InputError
    from dronecap.nerf.geometry import extract, write_geometry
    from dronecap.nerf.run_dir import open_run

    if not 0 < s.opacity < 1:
        raise InputError(f"--opacity must be strictly between 0 and 1, got {s.opacity}")
    check_threads(s.threads)
    use_torch_threads(s.threads)
    trainer, _ = open_run(s.run_dir, s.dataset)
    out = Path(s.output) if s.output else Path(s.run_dir) / "geometry"
    geo = extract(trainer, s.resolution, s.opacity)
    write_geometry(geo, out)
    print(
        f"wrote {out}/mesh.ply ({len(geo.vertices)} vertices, {len(geo.faces)} triangles) and "
        f"{out}/points.ply; surface at density {geo.level:.3g} per scene unit"
    )
    if geo.far is not None:
        print(f"the far field ({geo.far['kind']}): {out}/far_field.json, {out}/far_field.png")
    return 0
