"""frames.h5 from one or several drones' sources: which sources a swarm is, and the file itself.

``dronecap ingest A.mp4 B.mp4 ...`` (one source per drone, in that order) or
``dronecap ingest SWARM_FOLDER`` (:func:`drone_sources`: the entries listed in its
``swarm.json``, or else its videos or capture folders in name order) ingests every source on its
own (selection per flight, as for one) and :func:`frames_dataset` joins them in one file: every
frame records its drone (``/drone``: the source's position) and its index in that source
(``/source_index``); each drone has its own camera (``cameras`` + ``/camera_index``) when its
calibration is known. Frame names are prefixed by the drone's name (``drone_0:frame_000012``),
so names stay unique across drones. The per-decoded-frame tables of every drone are stored one
after the other with ``extra/decoded_drone`` naming each row's drone.

:func:`replay` re-runs one flight's selection on the tables a frames.h5 stores (``dronecap ingest
--replay``), without decoding.
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np

from dronecap.capture.decode import IMAGE_SUFFIXES
from dronecap.capture.ingest import IngestParams, IngestResult, params_record
from dronecap.capture.selection import SelectionParams, select_frames
from dronecap.capture.tables import TELEMETRY_NAMES, extra_to_tables, tables_to_extra
from dronecap.datasets.format import Dataset, open_dataset, provenance
from dronecap.errors import InputError
from dronecap.files import sha256_file

SWARM_FILE = "swarm.json"  # what `dronecap simulate --drones N` writes beside the drones
NOT_A_SOURCE = {".json", ".csv", ".txt", ".md", ".yaml", ".yml", ".h5"}


def drone_sources(given: list[str]) -> list[Path]:
    """The sources, one per drone, of ``given`` paths: several paths as they are; one folder
    that is a swarm (a ``swarm.json``, or no images and no telemetry CSV of its own but several
    videos or folders) as its entries; anything else as itself.

    Raises:
        InputError: a missing path, a source given twice, or videos and folders mixed.
    """
    paths = [Path(p) for p in given]
    for p in paths:
        if not p.exists():
            raise InputError("no such file or folder", p)
    if len(paths) == 1 and paths[0].is_dir():
        paths = _swarm_entries(paths[0]) or paths
    seen: dict[Path, Path] = {}
    for p in paths:
        key = p.resolve()
        if key in seen:
            raise InputError(f"is given twice (also as {seen[key]}): one source per drone", p)
        seen[key] = p
    kinds = {p.is_dir() for p in paths}
    if len(kinds) > 1:
        video = next(p for p in paths if not p.is_dir())
        folder = next(p for p in paths if p.is_dir())
        raise InputError(
            f"sources of different kinds mixed: {video} is a video, {folder} a folder;"
            " give one kind for every drone"
        )
    return paths


def _swarm_entries(folder: Path) -> list[Path] | None:
    """The drones' sources in ``folder`` when it is a swarm folder, else None."""
    listing = folder / SWARM_FILE
    if listing.is_file():
        try:
            doc = json.loads(listing.read_text())
            entries = [folder / str(d["entry"]) for d in doc["drones"]]
        except (OSError, ValueError, KeyError, TypeError) as err:
            raise InputError(f"not a readable swarm listing: {err}", listing) from None
        return entries
    items = sorted(folder.iterdir())
    own = [p for p in items if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES | {".csv"}]
    entries = [
        p for p in items if not p.name.startswith(".") and p.suffix.lower() not in NOT_A_SOURCE
    ]
    return entries if not own and len(entries) >= 2 else None


def drone_name(source: Path) -> str:
    """A drone's name: its source's file stem or folder name."""
    return source.stem if source.is_file() else source.name


def frames_dataset(
    results: list[IngestResult], sources: list[Path], params: list[IngestParams]
) -> Dataset:
    """The frames.h5 content of one ingest result per drone (sources and params alike).

    One source gives today's single-flight file (drone 0, its camera as ``intrinsics``);
    several give a drone and a camera per frame (module docstring).

    Raises:
        InputError: some drones have a known camera and others none (give a calibration for
            every drone or for none).
    """
    names = [drone_name(s) for s in sources]
    if len(set(names)) < len(names):
        names = [f"drone_{d}_{n}" for d, n in enumerate(names)]
    counts = [len(r.images) for r in results]
    drone = np.repeat(np.arange(len(results)), counts).astype(np.int16)
    single = len(results) == 1
    hashes = {str(s): sha256_file(s) for s in sources}
    record = params_record(params[0])
    if not single:
        record["intrinsics"] = [p.intrinsics for p in params]
    ds = Dataset(
        kind="frames",
        images=np.concatenate([r.images for r in results]),
        names=[
            f"{n}:{x}" if not single else x
            for n, r in zip(names, results, strict=True)
            for x in r.names
        ],
        source_index=np.concatenate([r.tables["source_index"][r.kept_index] for r in results]),
        timestamps=np.concatenate([r.tables["timestamp"][r.kept_index] for r in results]),
        extra=_joined_extra(results),
        attrs=results[0].summary() if single else _swarm_summary(results, names),
        provenance=provenance("ingest", record, hashes),
        drone=drone,
        drone_names=names,
    )
    cams = [r.camera for r in results]
    if single:  # today's layout: the one camera as `intrinsics` (stages that refine it set it)
        ds.intrinsics = cams[0]
    elif all(c is not None for c in cams):
        ds.set_cameras(cams, drone)  # type: ignore[arg-type]
    elif any(c is not None for c in cams):
        unknown = [n for n, c in zip(names, cams, strict=True) if c is None]
        raise InputError(
            f"drones {', '.join(unknown)} have no camera calibration while others do: give"
            " --intrinsics for every drone (once each, in order) or for none"
        )
    return ds


def _joined_extra(results: list[IngestResult]) -> dict[str, np.ndarray]:
    """Every drone's ``/extra`` tables one after the other (``decoded_drone`` marks the rows);
    a drone without telemetry gets invalid priors where others have them."""
    extras = [tables_to_extra(r.tables, r.selection) for r in results]
    if len(extras) == 1:
        return extras[0]
    keys = set().union(*extras)
    for r, e in zip(results, extras, strict=True):
        n_dec, n_kept = len(r.selection.keep), len(r.images)
        for k in keys - set(e):
            like = next(x[k] for x in extras if k in x)
            rows = n_kept if k in ("prior_c2w", "prior_valid", "frame_id") else n_dec
            e[k] = _missing(like, rows, k)
    out = {k: np.concatenate([e[k] for e in extras]) for k in keys if k != "reason_legend"}
    out["reason_legend"] = extras[0]["reason_legend"]
    sizes = [len(r.selection.keep) for r in results]
    out["decoded_drone"] = np.repeat(np.arange(len(results)), sizes).astype(np.int16)
    return out


def _missing(like: np.ndarray, rows: int, key: str) -> np.ndarray:
    """``rows`` rows shaped like ``like`` that say "no value": identity priors, invalid, -1."""
    if key in ("prior_c2w", TELEMETRY_NAMES["prior_c2w"]):
        return np.tile(np.eye(4), (rows, 1, 1))
    fill = {"b": False, "f": np.nan, "i": -1, "u": 0}.get(like.dtype.kind, 0)
    return np.full((rows, *like.shape[1:]), fill, like.dtype)


def _swarm_summary(results: list[IngestResult], names: list[str]) -> dict[str, object]:
    """The stage attrs of a swarm's file: totals and every drone's own summary."""
    per = [r.summary() | {"drone": n} for r, n in zip(results, names, strict=True)]
    return {
        "drones": per,
        "decoded": sum(int(s["decoded"]) for s in per),  # type: ignore[call-overload]
        "kept": sum(int(s["kept"]) for s in per),  # type: ignore[call-overload]
        "size": per[0]["size"],
        "warnings": [f"{p['drone']}: {w}" for p in per for w in p["warnings"]],  # type: ignore[attr-defined]
    }


def replay(
    path: Path, changes: dict[str, object], subset: bool
) -> tuple[list[str], Dataset | None]:
    """Re-run the selection of the one-flight frames file ``path`` with ``changes`` to its
    stored selection parameters, on its stored tables (no decoding).

    Returns:
        (the lines to print: what is kept and dropped, and a note when these options would
        keep frames that were not stored; with ``subset``, the re-selected frames as a
        Dataset, else None).

    Raises:
        InputError: not a frames file, one of several drones, or no stored tables.
    """
    ds = open_dataset(path, kinds=("frames",))
    if len(ds.drone_names or []) > 1:
        raise InputError("holds several drones: --replay reads one flight's file", path)
    try:
        tables = extra_to_tables(ds.extra)
    except InputError as err:
        raise InputError(str(err), path) from None
    stored = ds.provenance.get("params", {}).get("selection", {})
    known = {f.name for f in dataclasses.fields(SelectionParams)}
    params = SelectionParams(**{k: v for k, v in stored.items() if k in known}).replace(**changes)
    old_keep = np.asarray(ds.extra["keep"], bool)
    free = select_frames(tables, params)  # what a re-ingest with these options would keep
    sel = select_frames(tables, params, available=old_keep)  # among the stored images
    counts = sel.counts()
    dropped = ", ".join(f"{k} {v}" for k, v in counts.items() if not k.startswith("kept"))
    lines = [
        f"replay of {path}: {len(sel.keep)} decoded frames, kept {int(sel.keep.sum())} of the "
        f"{int(old_keep.sum())} stored; dropped: {dropped or 'none'}"
        f"; min_motion {sel.min_motion:.2f} px"
    ]
    extra = int((free.keep & ~old_keep).sum())
    if extra:
        lines.append(
            f"note: {extra} frames that these options would keep were not stored; re-run "
            "`dronecap ingest SOURCE` with them to get those images"
        )
    if not subset:
        return lines, None
    stored_pos = np.flatnonzero(old_keep)  # decoded position of each stored image
    sub = ds.subset(np.flatnonzero(np.isin(stored_pos, np.flatnonzero(sel.keep))))
    sub.extra = tables_to_extra(tables, sel)
    sub.attrs = {
        **ds.attrs,
        "kept": int(sel.keep.sum()),
        "dropped": {k: v for k, v in counts.items() if not k.startswith("kept")},
        "min_motion_used": sel.min_motion,
        "replayed_from": str(path),
    }
    record = {**ds.provenance.get("params", {}), "selection": dataclasses.asdict(params)}
    sub.provenance = {**ds.provenance, "params": record}
    return lines, sub
