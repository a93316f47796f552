"""`dronecap import-transforms`: an instant-ngp / nerfstudio dataset -> dataset.h5."""

from __future__ import annotations

from dataclasses import dataclass

from dronecap.settings import Settings as Base
from dronecap.settings import output_setting, setting


@dataclass(kw_only=True)
class ImportOptions(Base):
    """The options every scene importer shares: output, stored width, colour."""

    output: str | None = output_setting("dataset to write", "WORKDIR/dataset.h5")
    size: int = setting(160, minimum=8, help="stored image width in pixels, >= 8")
    color: str = setting(
        "auto",
        choices=("auto", "rgb", "gray"),
        help="stored colour; auto: gray when every image is gray",
    )
    allow_outside: bool = setting(
        False, help="read images named outside the source folder ('..', absolute, links out)"
    )


@dataclass(kw_only=True)
class Settings(ImportOptions):
    """Options of ``dronecap import-transforms``."""

    source: str = setting(
        positional=True,
        help="folder with transforms.json or transforms_{train,val,test}.json, or a .json file",
    )


def run(s: Settings) -> int:
    """Import and print what was stored."""
    from dronecap import workspace
    from dronecap.datasets.import_scene import check_options, describe
    from dronecap.datasets.import_transforms import import_transforms
    from dronecap.datasets.safe_paths import outside_allowed

    check_options(s.size, s.color)
    out = workspace.resolve(s.workdir, s.output, workspace.DATASET)
    with outside_allowed(s.allow_outside):
        print(describe(import_transforms(s.source, out, size=s.size, color=s.color)))
    return 0
