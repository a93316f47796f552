"""`dronecap import-blender`: a NeRF Synthetic 360° scene (Blender layout) -> dataset.h5."""

from __future__ import annotations

from dataclasses import dataclass

from dronecap.settings import Settings as Base
from dronecap.settings import output_setting, setting


@dataclass(kw_only=True)
class Settings(Base):
    """Options of ``dronecap import-blender``."""

    scene_dir: str = setting(
        positional=True, help="scene folder holding transforms_{train,val,test}.json"
    )
    output: str | None = output_setting("dataset to write", "WORKDIR/dataset.h5")
    resolution: int = setting(160, help="stored image width in pixels (default 160)")
    color: str = setting("rgb", choices=("rgb", "gray"), help="stored colour (default rgb)")
    allow_outside: bool = setting(
        False, help="read images named outside the source folder ('..', absolute, links out)"
    )


def run(s: Settings) -> int:
    """Import the scene and print where it went."""
    from dronecap import workspace
    from dronecap.datasets.blender import import_blender
    from dronecap.datasets.format import open_dataset
    from dronecap.datasets.safe_paths import outside_allowed

    out = workspace.resolve(s.workdir, s.output, workspace.DATASET)
    with outside_allowed(s.allow_outside):
        path = import_blender(s.scene_dir, out, resolution=s.resolution, color=s.color)
    ds = open_dataset(path)
    counts = ", ".join(f"{len(ds.indices(k))} {k}" for k in ("train", "val", "test"))
    lo, hi = ds.aabb
    print(f"wrote {path}: {ds.n} views {ds.hw[1]}x{ds.hw[0]}x{ds.channels} ({counts})")
    print(f"aabb {lo.round(3).tolist()} .. {hi.round(3).tolist()} ({ds.attrs['bounds_from']})")
    return 0
