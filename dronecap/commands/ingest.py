"""``dronecap ingest``: flight video or drone capture folder -> 160x160 gray selected frames.h5.

Several sources (``dronecap ingest A.mp4 B.mp4``) or a swarm folder (one video or capture
folder per drone, e.g. ``dronecap simulate --drones N``'s) give one file with a drone and a
camera per frame (:mod:`dronecap.capture.frames_file`).

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

from dronecap.capture.framing import parse_size
from dronecap.capture.selection import SelectionParams
from dronecap.settings import Numbers, Size, flatten, numbers, output_setting, setting
from dronecap.settings import Settings as Base

# The settings that are IngestParams fields of the same name, passed on as given.
AS_GIVEN = ("crop", "fps", "allow_truncated", "skip_unreadable", "telemetry", "columns")


def _size(text: str) -> Size:
    """``"160"`` or ``"WxH"`` -> the output size (ValueError when it is not one)."""
    return Size(parse_size(text))


@dataclass(kw_only=True)
class Settings(Base):
    """Options of ``dronecap ingest`` (the selection's are SelectionParams' fields)."""

    source: list[str] = setting(
        factory=list,
        positional=True,
        help="video file or folder of images; several (one per drone, in order) or a swarm "
        "folder (one video or capture folder per drone) for a swarm",
    )
    output: str | None = output_setting("output frames file", "WORKDIR/frames.h5")
    size: Size = setting(
        Size((160, 160)), parse=_size, late=True, help="output size, '160' or 'WxH' (default: 160)"
    )
    crop: str = setting(
        "center",
        help="'center' (crop to the output aspect, default), 'stretch', or 'X,Y,W,H' in source px",
    )
    intrinsics: list[str] = setting(
        factory=list,
        repeat=True,
        help="source camera: 'fx,fy,cx,cy' (source pixels), a `dronecap calibrate` JSON, an "
        "OpenCV YAML/XML calibration or the simulator's flight.json (distortion is kept); "
        "default: SOURCE_STEM.json beside the video if it has intrinsics; 'none' to ignore it. "
        "Several drones: once for all, once per drone in order, or a folder of DRONE.json",
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
    camera_offset: Numbers | None = setting(
        None,
        parse=numbers(3),
        late=True,
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
    from dronecap.capture.frames_file import drone_sources, frames_dataset
    from dronecap.capture.ingest import IngestParams, ingest
    from dronecap.capture.telemetry import parse_columns
    from dronecap.datasets import write_dataset
    from dronecap.errors import InputError

    sources = drone_sources(args.source)
    calibrations = _calibrations(args.intrinsics, sources)
    try:
        parse_columns(args.columns)
    except ValueError as err:
        raise InputError(str(err)) from None
    offset = args.camera_offset
    if offset is not None and not all(abs(v) < 10 for v in offset):
        raise InputError(f"--camera-offset: metres within 10 m, got {offset}")
    if args.telemetry is not None and len(sources) > 1:
        raise InputError(
            "--telemetry names one CSV: with several drones each capture folder's own is used"
        )
    common = IngestParams(
        size=tuple(args.size),
        camera_offset=None if offset is None else tuple(offset),
        bayer=args.bayer.lower() if args.bayer in ("AUTO", "NONE") else args.bayer,
        selection=selection,  # type: ignore[arg-type]
        **{name: getattr(args, name) for name in AS_GIVEN},
    )
    params = [dataclasses.replace(common, intrinsics=c) for c in calibrations]
    out = workspace.resolve(args.workdir, args.output, workspace.FRAMES)
    results = [ingest(s, p) for s, p in zip(sources, params, strict=True)]
    write_dataset(out, frames_dataset(results, sources, params))
    several = len(sources) > 1
    for source, p, result in zip(sources, params, results, strict=True):
        label = f"{source}: " if several else ""
        for w in result.warnings:
            print(f"dronecap ingest: warning: {label}{w}", file=sys.stderr)
        if p.intrinsics is not None and not args.intrinsics:
            print(f"{label}intrinsics from {p.intrinsics}")
        print(f"{label}{result.summary_line()}" + ("" if several else f" -> {out}"))
    if several:
        print(f"{len(sources)} drones, {sum(len(r.images) for r in results)} frames -> {out}")
    return 0


def _calibrations(given: list[str], sources: list[Path]) -> list[str | None]:
    """Each drone's calibration: none given, its sidecar (``flight.json``); one, for all (a
    folder: its DRONE.json/.yaml/.xml); one per drone, in order. 'none' ignores the sidecar."""
    from dronecap.capture.frames_file import drone_name
    from dronecap.errors import InputError

    if not given:
        return [_sidecar_calibration(s) for s in sources]
    if len(given) == 1 and Path(given[0]).is_dir():
        folder, out = Path(given[0]), []
        for s in sources:
            found = [folder / f"{drone_name(s)}{x}" for x in (".json", ".yaml", ".yml", ".xml")]
            found = [p for p in found if p.is_file()]
            if not found:
                raise InputError(f"holds no calibration {drone_name(s)}.json for drone {s}", folder)
            out.append(str(found[0]))
        return out
    if len(given) not in (1, len(sources)):
        raise InputError(
            f"--intrinsics given {len(given)} times for {len(sources)} drones: give it once"
            " (for all) or once per drone, in the sources' order"
        )
    each = given * len(sources) if len(given) == 1 else given
    return [None if g.lower() == "none" else g for g in each]


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
    from dronecap.capture.frames_file import replay
    from dronecap.datasets import write_dataset

    lines, sub = replay(Path(args.replay), changes, args.output is not None)
    print("\n".join(lines))
    if sub is not None:
        write_dataset(args.output, sub)
        print(f"wrote {sub.n} frames -> {args.output}")
    return 0
