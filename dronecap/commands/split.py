"""`dronecap split`: train/test split of a posed flight -> dataset.h5."""

from __future__ import annotations

from dataclasses import dataclass

from dronecap.settings import Settings as Base
from dronecap.settings import input_setting, output_setting, setting


@dataclass(kw_only=True)
class Settings(Base):
    """Options of ``dronecap split``."""

    input: str | None = input_setting("posed flight", "WORKDIR/posed.h5")
    output: str | None = output_setting("dataset to write", "WORKDIR/dataset.h5")
    every: int = setting(8, minimum=2, help="hold out one frame in EVERY for test (default 8)")


def run(s: Settings) -> int:
    """Split and print the counts."""
    from dronecap import workspace
    from dronecap.datasets.format import open_dataset
    from dronecap.datasets.split import split_dataset

    src = workspace.resolve(s.workdir, s.input, workspace.POSED)
    out = workspace.resolve(s.workdir, s.output, workspace.DATASET)
    ds = open_dataset(split_dataset(src, out, every=s.every))
    counts = ", ".join(f"{len(ds.indices(k))} {k}" for k in ("train", "val", "test"))
    how = (
        "kept the input's split" if ds.provenance["params"]["kept_existing_split"] else "new split"
    )
    print(f"wrote {out}: {ds.n} frames ({counts}; {how})")
    return 0
