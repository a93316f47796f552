"""The report's record of every drone of a swarm: frames, registered, links, camera, accuracy.

Fields per drone (``report["drones"]``, docs/sfm.md "A swarm"): ``name``, ``frames`` (kept
frames in frames.h5), ``registered`` (in the swarm's model), ``links`` (drone name -> verified
frame pairs with the other drone's flight, :mod:`dronecap.sfm.links`), ``linked`` (in the
swarm's model's group), ``own_model`` (an unlinked drone: its own model's folder and frames),
``fx`` / ``fy`` (the camera used, px) and, with ground truth, ``ate_percent`` (of the whole
swarm's extent) and ``rot_median_deg`` in the swarm's one alignment.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from dronecap.camera import Camera
from dronecap.datasets.format import Dataset
from dronecap.sfm.camera_plan import CameraPlan


def drone_records(
    ds: Dataset, registered: np.ndarray, cameras: list[Camera], plan: CameraPlan, report: dict
) -> list[dict[str, Any]]:
    """One record per drone of ``ds`` (see the module docstring); ``registered``: int [R] the
    frames in the model; ``cameras``: the camera of every drone; ``report``: the sfm report so
    far (its "flights" and "accuracy" records)."""
    drones = ds.drones()
    n_drones = len(plan.cameras)
    flights = report.get("flights") or {}
    links = np.asarray(flights.get("links", np.zeros((n_drones, n_drones))), np.int64)
    main = flights.get("main", list(range(n_drones)))
    own = {d: u for u in flights.get("unlinked", []) for d in u["drones"]}
    per_group = (report.get("accuracy") or {}).get("per_group", {})
    out = []
    for d in range(n_drones):
        k = cameras[d]
        record: dict[str, Any] = {
            "name": ds.drone_name(d),
            "frames": int((drones == d).sum()),
            "registered": int((drones[registered] == d).sum()),
            "linked": d in main,
            "links": {ds.drone_name(j): int(links[d, j]) for j in range(n_drones) if j != d},
            "fx": round(k.fx, 3),
            "fy": round(k.fy, 3),
        }
        if d in own:
            record["own_model"] = {"model": own[d]["model"], "frames": own[d]["frames"]}
        record.update(per_group.get(str(d), {}))
        out.append(record)
    return out


def drone_lines(report: dict[str, Any]) -> list[str]:
    """The printed report's lines on a swarm's drones (none for a single flight)."""
    records = report.get("drones")
    if not records:
        return []
    lines = [f"  drones: {len(records)}, one model for the linked ones"]
    for r in records:
        links = ", ".join(f"{k} {v}" for k, v in r["links"].items() if v) or "none"
        acc = ""
        if "ate_percent" in r:
            acc = f", ATE {r['ate_percent']:.3g} %, rotation {r['rot_median_deg']:.3g} deg"
        lines.append(
            f"    {r['name']}: {r['registered']}/{r['frames']} registered, f {r['fx']:.1f} px, "
            f"links {links}{acc}"
        )
        if not r["linked"]:
            own = r.get("own_model") or {}
            lines.append(
                f"    WARNING {r['name']}: not linked to the other drones' flights: kept out of "
                f"the model; its own model: {own.get('frames', 0)} frames in "
                f"{own.get('model') or 'none'}"
            )
    return lines
