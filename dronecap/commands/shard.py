"""`dronecap shard`: IID, viewpoint-sector or per-drone shards of a dataset -> shards/."""

from __future__ import annotations

from dataclasses import dataclass

from dronecap.settings import Settings as Base
from dronecap.settings import input_setting, output_setting, setting


@dataclass(kw_only=True)
class Settings(Base):
    """Options of ``dronecap shard``."""

    input: str | None = input_setting("dataset to shard", "WORKDIR/dataset.h5")
    output: str | None = output_setting("folder to write", "WORKDIR/shards")
    clients: int = setting(
        4, minimum=1, help="number of drones K (default 4; --scheme drone: one per drone)"
    )
    scheme: str = setting(
        "sector",
        help="iid (seeded shuffle), sector (contiguous viewpoint sectors; default) or drone"
        " (each drone's own train frames, for a swarm's dataset)",
    )
    seed: int = setting(0, minimum=0, help="seed of the iid shuffle, >= 0 (default 0)")


def run(s: Settings) -> int:
    """Shard and print one line per drone."""
    import json

    from dronecap import workspace
    from dronecap.datasets.shard import SCHEMES, shard_dataset
    from dronecap.errors import InputError

    if s.scheme not in SCHEMES:
        raise InputError(f"--scheme must be one of {', '.join(SCHEMES)}, got {s.scheme!r}")
    src = workspace.resolve(s.workdir, s.input, workspace.DATASET)
    out = workspace.resolve(s.workdir, s.output, workspace.SHARDS)
    shard_dataset(src, out, clients=s.clients, scheme=s.scheme, seed=s.seed)
    summary = json.loads((out / "summary.json").read_text())
    print(f"wrote {out}: {s.scheme} shards, {len(summary['test_views'])} common test views")
    for shard in summary["shards"]:
        sector = ""
        if "azimuth_deg" in shard:
            a, b = shard["azimuth_deg"]
            sector = f", azimuth {a:.0f}..{b:.0f} deg ({shard['span_deg']:.0f} deg)"
        drone = f" of drone {shard['drone']}" if "drone" in shard else ""
        print(f"  {shard['file']}: {shard['n_train']} train views{drone}{sector}")
    return 0
