"""`dronecap export-transforms`: a dataset -> nerfstudio / instant-ngp / COLMAP files + images."""

from __future__ import annotations

from dataclasses import dataclass

from dronecap.settings import Settings as Base
from dronecap.settings import input_setting, output_setting, setting


@dataclass(kw_only=True)
class Settings(Base):
    """Options of ``dronecap export-transforms``."""

    input: str | None = input_setting("dataset to export", "WORKDIR/dataset.h5")
    output: str | None = output_setting("folder to write", "WORKDIR/transforms")
    sparse_model: str | None = setting(
        None,
        help="the COLMAP model the poses came from, for the coloured sparse cloud and the "
        "COLMAP observations (default: WORKDIR/sfm/model when it matches the dataset)",
    )


def run(s: Settings) -> int:
    """Export and say where."""
    import sys

    from dronecap import workspace
    from dronecap.datasets.export import export_transforms
    from dronecap.errors import InputError

    src = workspace.resolve(s.workdir, s.input, workspace.DATASET)
    out = workspace.resolve(s.workdir, s.output, workspace.TRANSFORMS)
    model = s.sparse_model
    default_model = workspace.resolve(s.workdir, None, workspace.SFM_DIR) / "model"
    found = default_model if default_model.is_dir() else None
    try:
        res = export_transforms(src, out, model or found)
    except InputError as err:
        if model is not None or not default_model.is_dir() or "COLMAP model" not in str(err):
            raise
        print(f"note: {default_model} not used ({err}); exporting without sparse points",
              file=sys.stderr)  # fmt: skip
        res = export_transforms(src, out, None)
    splits = ", ".join(f"{n} {k}" for k, n in res.split_counts.items()) or "no split"
    print(f"wrote {out / 'transforms.json'}: {res.frames} frames ({splits}), images in {out}")
    if res.split_files:
        print(f"instant-ngp: {', '.join(res.split_files)} (give it transforms_train.json)")
    pts = f"{res.points} coloured points" if res.points else "no sparse points"
    print(f"COLMAP model (binary, text) under {out}/colmap; {pts}")
    for note in res.notes:
        print(f"note: {note}")
    return 0
