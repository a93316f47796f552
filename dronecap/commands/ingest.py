"""``dronecap ingest``: flight video or drone capture folder -> 160x160 gray selected frames.h5.

``dronecap ingest flight.mp4`` (or a folder of frames, e.g. a NanoCockpit or PULP-Dronet capture
with its telemetry CSV) decodes, checks for stream defects, scores, tracks features and selects,
and writes ``frames.h5`` in the workspace (with pose priors when the telemetry has poses).
``dronecap ingest --replay frames.h5 --min-parallax 1.2`` re-runs only the selection on the
tables stored in the file (no decoding) and prints what would change; with ``-o`` it writes the
re-selected frames when all of them are stored.
"""

from __future__ import annotations

import dataclasses
import json
import math
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from dronecap.capture.selection import SelectionParams
from dronecap.stage import Settings as Base
from dronecap.stage import flatten, setting


@dataclass(kw_only=True)
class Settings(Base):
    """Options of ``dronecap ingest`` (the selection's are SelectionParams' fields)."""

    source: str | None = setting(None, positional=True, help="video file or folder of images")
    output: str | None = setting(
        None, short="-o", help="output frames file (default: WORKDIR/frames.h5)"
    )
    size: str = setting("160", help="output size, '160' or 'WxH' (default: 160)")
    crop: str = setting(
        "center",
        help="'center' (crop to the output aspect, default), 'stretch', or 'X,Y,W,H' in source px",
    )
    intrinsics: str | None = setting(
        None,
        help="source camera: 'fx,fy,cx,cy' (source pixels), a `dronecap calibrate` JSON, an "
        "OpenCV YAML/XML calibration or the simulator's flight.json (distortion is kept); "
        "default: SOURCE_STEM.json beside the video if it has intrinsics; 'none' to ignore it",
    )
    fps: float = setting(30.0, help="frame rate of an image folder")
    allow_truncated: bool = setting(
        False, help="ingest the frames a truncated video still holds instead of failing"
    )
    skip_unreadable: bool = setting(
        False, help="drop image files that do not decode instead of failing"
    )
    telemetry: str | None = setting(
        None,
        metavar="CSV",
        help="telemetry CSV of an image folder (default: the capture folder's metadata.csv, "
        "state.csv or a CSV with known columns; see docs/capture.md)",
    )
    columns: str | None = setting(
        None,
        help="map telemetry columns: 'file=COL,frame_id=COL,time=COL,x=COL,...,qw=COL' plus "
        "'unit=mm|m,time_unit=us|ms|s'",
    )
    camera_offset: str | None = setting(
        None,
        metavar="X,Y,Z",
        help="camera position in the drone's body axes, metres (default: at the body origin)",
    )
    bayer: str = setting(
        "AUTO",
        parse=str.upper,
        choices=("AUTO", "NONE", "RGGB", "BGGR", "GRBG", "GBRG"),
        help="raw Bayer mosaic in gray frames: detect (auto, default), none, or its pattern",
    )
    replay: str | None = setting(
        None,
        metavar="FRAMES_H5",
        help="re-run only the selection on the scores stored in FRAMES_H5 (no decoding)",
    )
    selection: dict[str, Any] = flatten(
        SelectionParams,
        help=lambda f: f"{f.metadata['help']} (default: {f.default})",
        group="frame selection",
    )


def run(args: Settings) -> int:
    """Ingest a source, or replay a stored selection."""
    from dronecap.errors import InputError

    changes = args.selection
    bad = SelectionParams().replace(**changes).problems()
    if not (args.fps > 0 and math.isfinite(args.fps)):
        bad.insert(0, f"--fps: must be a positive frame rate, got {args.fps}")
    if bad:
        raise InputError(bad[0])
    if args.replay:
        return _replay(args, changes)
    if not args.source:
        raise InputError("give a video file or image folder to ingest (or --replay FRAMES_H5)")
    return _ingest(args, SelectionParams().replace(**changes))


def _ingest(args: Settings, selection: object) -> int:
    from dronecap import workspace
    from dronecap.capture.framing import parse_numbers, parse_size
    from dronecap.capture.ingest import IngestParams, ingest, params_record, tables_to_extra
    from dronecap.capture.telemetry import parse_columns
    from dronecap.datasets import Dataset, provenance, write_dataset
    from dronecap.errors import InputError
    from dronecap.files import sha256_file

    source = Path(args.source)
    try:
        size = parse_size(args.size)
    except ValueError as err:
        raise InputError(f"--size: {err}") from None
    intrinsics = args.intrinsics
    if intrinsics is None:
        intrinsics = _sidecar_calibration(source)
    elif intrinsics.lower() == "none":
        intrinsics = None
    try:
        parse_columns(args.columns)
    except ValueError as err:
        raise InputError(str(err)) from None
    offset = None
    if args.camera_offset is not None:
        try:
            offset = parse_numbers(args.camera_offset, 3, float, "--camera-offset: give X,Y,Z")
        except ValueError as err:
            raise InputError(str(err)) from None
        if not all(math.isfinite(v) and abs(v) < 10 for v in offset):
            raise InputError(f"--camera-offset: metres within 10 m, got {args.camera_offset}")
    params = IngestParams(
        size=size,
        crop=args.crop,
        fps=args.fps,
        intrinsics=intrinsics,
        allow_truncated=args.allow_truncated,
        skip_unreadable=args.skip_unreadable,
        telemetry=args.telemetry,
        columns=args.columns,
        camera_offset=offset,
        bayer=args.bayer.lower() if args.bayer in ("AUTO", "NONE") else args.bayer,
        selection=selection,  # type: ignore[arg-type]
    )
    out = workspace.resolve(args.workdir, args.output, workspace.FRAMES)
    result = ingest(source, params)
    kept = result.kept_index
    cam = result.camera
    ds = Dataset(
        kind="frames",
        images=result.images,
        names=result.names,
        source_index=result.tables["source_index"][kept],
        timestamps=result.tables["timestamp"][kept],
        intrinsics=cam,
        extra=tables_to_extra(result.tables, result.selection),
        attrs=result.summary(),
        provenance=provenance("ingest", params_record(params), {str(source): sha256_file(source)}),
    )
    write_dataset(out, ds)
    for w in result.warnings:
        print(f"dronecap ingest: warning: {w}", file=sys.stderr)
    if intrinsics is not None and args.intrinsics is None:
        print(f"intrinsics from {intrinsics}")
    print(f"{result.summary_line()} -> {out}")
    return 0


def _sidecar_calibration(source: Path) -> str | None:
    """``flight.json`` beside ``flight.mp4`` (or inside a capture folder) when it holds
    intrinsics (the simulator writes it)."""
    side = source / "flight.json" if source.is_dir() else source.with_suffix(".json")
    if not source.exists() or not side.is_file():
        return None
    try:
        doc = json.loads(side.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError):
        return None
    return str(side) if isinstance(doc, dict) and isinstance(doc.get("intrinsics"), dict) else None


def _replay(args: Settings, changes: dict[str, object]) -> int:
    import numpy as np

    from dronecap.capture.ingest import extra_to_tables, tables_to_extra
    from dronecap.capture.selection import SelectionParams, select_frames
    from dronecap.datasets import open_dataset, write_dataset
    from dronecap.errors import InputError

    path = Path(args.replay)
    ds = open_dataset(path, kinds=("frames",))
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
    n = len(sel.keep)
    counts = sel.counts()
    dropped = ", ".join(f"{k} {v}" for k, v in counts.items() if not k.startswith("kept"))
    print(
        f"replay of {path}: {n} decoded frames, kept {int(sel.keep.sum())} of the "
        f"{int(old_keep.sum())} stored; dropped: {dropped or 'none'}"
        f"; min_motion {sel.min_motion:.2f} px"
    )
    extra = int((free.keep & ~old_keep).sum())
    if extra:
        print(
            f"note: {extra} frames that these options would keep were not stored; re-run "
            "`dronecap ingest SOURCE` with them to get those images"
        )
    if args.output is None:
        return 0
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
    write_dataset(args.output, sub)
    print(f"wrote {sub.n} frames -> {args.output}")
    return 0
