"""`dronecap import-colmap`: a COLMAP sparse model + its images folder -> dataset.h5."""

from __future__ import annotations

from dataclasses import dataclass

from dronecap.commands.import_transforms import ImportOptions
from dronecap.settings import setting


@dataclass(kw_only=True)
class Settings(ImportOptions):
    """Options of ``dronecap import-colmap``."""

    model: str = setting(
        positional=True, help="COLMAP model folder (cameras/images/points3D .bin or .txt)"
    )
    images: str = setting(positional=True, help="folder the model's image names are relative to")


def run(s: Settings) -> int:
    """Import and print what was stored."""
    from dronecap import workspace
    from dronecap.datasets.import_colmap import import_colmap
    from dronecap.datasets.import_scene import check_options, describe
    from dronecap.datasets.safe_paths import outside_allowed

    check_options(s.size, s.color)
    out = workspace.resolve(s.workdir, s.output, workspace.DATASET)
    with outside_allowed(s.allow_outside):
        print(describe(import_colmap(s.model, s.images, out, size=s.size, color=s.color)))
    return 0
