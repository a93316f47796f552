"""The ingest stage: decode a flight, convert every frame to small gray, score it, select frames.

:func:`ingest` returns an :class:`IngestResult` (kept images, per-decoded-frame tables, the
decision and a summary) and never writes files; the ``dronecap ingest`` command stores the result
as ``frames.h5``. Every decoded frame is converted (demosaic, gray, crop, area resize) and scored
(:mod:`.quality`) in a background thread while the main thread checks it for stream defects
(:mod:`.defects`) and tracks features through it (:mod:`.tracks`), so the two halves overlap on
two cores. Telemetry of a capture folder (:mod:`.telemetry`) is read and checked before any
frame is decoded.
"""

from __future__ import annotations

import time
from collections.abc import Iterator, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from dronecap.camera import Camera
from dronecap.camera.files import load_camera
from dronecap.capture.decode import (
    DecodedFrame,
    ImageFolderSource,
    SourceInfo,
    VideoSource,
    open_source,
    prefetch,
    progress_stream,
)
from dronecap.capture.defects import UpsideDownCheck, demosaic, detect_bayer, torn_row
from dronecap.capture.framing import LUMA_WEIGHTS, Framing, make_framing
from dronecap.capture.quality import SCORE_NAMES, frame_diff, frame_scores
from dronecap.capture.selection import (
    REASONS,
    TORN,
    UPSIDE_DOWN,
    Selection,
    SelectionParams,
    select_frames,
)
from dronecap.capture.telemetry import Telemetry, find_capture, layout_for, match, parse_columns
from dronecap.capture.tracks import WINDOW, FeatureTracker
from dronecap.errors import InputError

MIN_KEPT = 2  # fewer kept frames leave nothing to reconstruct
DEFECTS_LISTED = 10  # frames named per defect in the warnings (all are in frames.h5)


@dataclass
class IngestParams:
    """Options of the ingest stage (the CLI's flags)."""

    size: tuple[int, int] = (160, 160)  # output (width, height) in pixels
    crop: str = "center"  # "center", "stretch" or "X,Y,W,H" (see framing.make_framing)
    fps: float = 30.0  # frame rate assumed for an image folder
    intrinsics: str | None = None  # "fx,fy,cx,cy" or a calibration file (camera.files); None
    allow_truncated: bool = False  # keep what decodes from a truncated video
    skip_unreadable: bool = False  # drop image files that do not decode instead of failing
    telemetry: str | None = None  # telemetry CSV; None: the capture folder's own, if any
    columns: str | None = None  # "--columns" mapping of canonical names to CSV columns
    camera_offset: tuple[float, float, float] | None = None  # camera in body axes (m)
    bayer: str = "auto"  # "auto" (detect), "none", or a pattern (RGGB, BGGR, GRBG, GBRG)
    selection: SelectionParams = field(default_factory=SelectionParams)


@dataclass
class IngestResult:
    """Everything the ingest stage produced (N decoded frames, M kept)."""

    info: SourceInfo
    framing: Framing
    camera: Camera | None  # camera (with distortion) of the output frames, when known
    camera_source: str  # "calibration", "flight.json" or "none"
    images: np.ndarray  # uint8 [M, h, w, 1] kept frames
    names: list[str]  # [M]
    tables: dict[str, np.ndarray]  # per decoded frame [N]: scores, source_index, timestamp
    selection: Selection  # keep mask and reason [N]
    telemetry: Telemetry | None  # matched telemetry of the decoded frames, if any
    bayer: str | None  # Bayer pattern demosaiced, if the source was a raw mosaic
    warnings: list[str]
    seconds: float  # wall time of decode + scoring + selection

    @property
    def kept_index(self) -> np.ndarray:
        """Positions of the kept frames among the decoded ones, int64 [M]."""
        return np.flatnonzero(self.selection.keep)

    def summary(self) -> dict[str, object]:
        """Small JSON-able record of the run (stored as the dataset's stage attrs)."""
        n = len(self.selection.keep)
        dropped = {k: v for k, v in self.selection.counts().items() if not k.startswith("kept")}
        return {
            "source": str(self.info.path),
            "source_kind": self.info.kind,
            "source_size": [self.info.width, self.info.height],
            "source_fps": self.info.fps,
            "codec": self.info.codec,
            "expected_frames": self.info.expected_frames,
            "decoded": n,
            "kept": int(self.selection.keep.sum()),
            "kept_for_gaps": int((self.selection.reason == 1).sum()),
            "dropped": dropped,
            "min_motion_used": self.selection.min_motion,
            "coverage_gaps": [list(g) for g in self.selection.gaps],
            "camera_source": self.camera_source,
            "bayer": self.bayer,
            "defects": self.defects(),
            "crop_box": list(self.framing.box),
            "size": list(self.framing.size),
            "luma_weights": LUMA_WEIGHTS,
            "run_fps": n / max(self.seconds, 1e-9),
            "warnings": self.warnings,
        } | ({"telemetry": self.telemetry.record()} if self.telemetry else {})

    def defects(self) -> dict[str, list[int]]:
        """Decoded frame positions of each stream defect: torn, upside_down, frozen,
        unreadable (empty lists omitted)."""
        return {k: [int(i) for i in v] for k, v in _defects(self.selection).items()}

    def summary_line(self) -> str:
        """One line: decoded, kept, dropped by reason, speed of the run."""
        s = self.summary()
        dropped = ", ".join(f"{k} {v}" for k, v in s["dropped"].items()) or "none"  # type: ignore[union-attr]
        line = f"decoded {s['decoded']} frames, kept {s['kept']}, dropped: {dropped}"
        if self.telemetry is not None:
            t = self.telemetry
            line += (
                f"; telemetry {t.layout} matched {int(t.prior_valid.sum())}/{len(t.prior_valid)}"
                f", {len(t.dropped)} frames lost in transmission"
            )
        if self.bayer:
            line += f"; raw Bayer {self.bayer} mosaic demosaiced"
        return line + f" ({s['run_fps']:.0f} frames/s)"


def ingest(source: str | Path, params: IngestParams, progress: bool = True) -> IngestResult:
    """Decode ``source`` (video file or image folder), score every frame and select frames.

    Raises:
        InputError: missing/unreadable source, no decodable frame, a truncated video (unless
            ``params.allow_truncated``), or fewer than two usable frames (nothing to
            reconstruct: black, blank or frozen footage).
    """
    t0 = time.perf_counter()
    src, telemetry = _open(Path(source), params)
    info = src.info
    try:
        framing = make_framing((info.width, info.height), params.size, params.crop)
    except ValueError as err:
        raise InputError(str(err), info.path) from None
    camera, camera_source = None, "none"
    if params.intrinsics is not None:
        source_camera, camera_source = load_camera(params.intrinsics, (info.width, info.height))
        camera = framing.camera(source_camera)
    warnings: list[str] = []
    if framing.upsamples:
        warnings.append(
            f"crop {framing.box[2]}x{framing.box[3]} is smaller than the output "
            f"{framing.size[0]}x{framing.size[1]}: frames are upsampled (no added detail)"
        )

    window = max(WINDOW, params.selection.max_gap)  # pair tables must reach max_gap frames back
    small, tables, bayer = _decode_and_score(
        src.frames(), framing, info, params.bayer, window, progress
    )
    warnings += _check_count(len(small), info, params.allow_truncated)
    if telemetry is not None:
        tables.update(_telemetry_tables(telemetry, tables["readable"]))
    selection = select_frames(tables, params.selection)
    kept = np.flatnonzero(selection.keep)
    if len(kept) < MIN_KEPT:
        raise InputError(_nothing_to_reconstruct(len(small), selection), info.path)
    warnings += _selection_warnings(selection, tables["name"], telemetry)
    return IngestResult(
        info=info,
        framing=framing,
        camera=camera,
        camera_source=camera_source,
        images=np.stack([small[i] for i in kept])[..., None],
        names=[tables["name"][i] for i in kept],
        tables={k: v for k, v in tables.items() if k != "name"},
        selection=selection,
        telemetry=telemetry,
        bayer=bayer,
        warnings=warnings,
        seconds=time.perf_counter() - t0,
    )


def _open(
    path: Path, params: IngestParams
) -> tuple[VideoSource | ImageFolderSource, Telemetry | None]:
    """The frame source of ``path`` and its matched telemetry (a capture folder's own CSV, or
    ``params.telemetry``), checked before any frame is decoded."""
    csv_path, layout = None, None
    if path.is_dir():
        path, csv_path, layout = find_capture(path)
    if params.telemetry is not None:
        csv_path, layout = Path(params.telemetry), None
        if not csv_path.is_file():
            raise InputError("telemetry file not found", csv_path)
    src = open_source(path, params.fps, params.skip_unreadable)
    if csv_path is None:
        return src, None
    if src.info.kind != "images":
        raise InputError(
            "telemetry is matched to the frames of an image folder, not a video", csv_path
        )
    try:
        columns = parse_columns(params.columns)
    except ValueError as err:
        raise InputError(str(err)) from None
    names = [f.name for f in src.files]  # type: ignore[union-attr]
    offset = None if params.camera_offset is None else np.asarray(params.camera_offset, float)
    return src, match(csv_path, layout_for(csv_path, columns, layout), names, offset)


def _check_count(n: int, info: SourceInfo, allow_truncated: bool) -> list[str]:
    """Refuse fewer than two decoded frames, or a truncated video unless ``allow_truncated``
    (then the warning about it)."""
    if n == 0:
        raise InputError("no decodable frames (empty or damaged video stream)", info.path)
    warnings = []
    expected = info.expected_frames
    if info.kind == "video" and expected is not None and n < expected - 1:
        msg = f"truncated: decoded {n} of {expected} frames ({100 * n / expected:.0f}%)"
        if not allow_truncated:
            raise InputError(f"{msg}; pass --allow-truncated to ingest those {n}", info.path)
        warnings.append(msg)
    if n == 1:
        raise InputError(
            "only one decodable frame: a single view has nothing to reconstruct", info.path
        )
    return warnings


def _selection_warnings(
    selection: Selection, names: np.ndarray, telemetry: Telemetry | None
) -> list[str]:
    """What the selection and the telemetry found: coverage gaps, frames dropped for stream
    defects, frames without a telemetry pose, frames lost in transmission."""
    warnings = []
    n = len(selection.keep)
    if selection.gaps:
        warnings.append(
            "coverage gaps with no usable frame: "
            + ", ".join(f"frames {a}-{b}" for a, b in selection.gaps)
        )
    for name, at in _defects(selection).items():
        warnings.append(f"{len(at)} {name.replace('_', '-')} frames dropped: " + _listed(names[at]))
    if telemetry is not None and not telemetry.prior_valid.all():
        missing = int((~telemetry.prior_valid).sum())
        warnings.append(
            f"{missing} of {n} frames have no telemetry pose (no row for them, or none within "
            f"20 ms): they get no prior (prior_valid False)"
        )
    if telemetry is not None and telemetry.dropped:
        lost = telemetry.dropped
        warnings.append(f"{len(lost)} camera frames lost in transmission: {_listed(lost)}")
    return warnings


def _listed(items: Sequence[object]) -> str:
    """The first :data:`DEFECTS_LISTED` items, comma-separated, and how many more there are."""
    listed = ", ".join(str(x) for x in items[:DEFECTS_LISTED])
    more = f" and {len(items) - DEFECTS_LISTED} more" if len(items) > DEFECTS_LISTED else ""
    return listed + more


def _decode_and_score(
    frames: Iterator[DecodedFrame],
    framing: Framing,
    info: SourceInfo,
    bayer: str,
    window: int,
    progress: bool,
) -> tuple[list[np.ndarray], dict[str, np.ndarray], str | None]:
    """Convert, check and score every frame.

    Returns the small frames, the tables [N] (scores, ``defect`` codes, pair tables of the
    feature tracks) and the Bayer pattern demosaiced (None: not a mosaic).
    """
    from dronecap.progress import progress_bar

    pattern: list[str | None] = [None if bayer == "none" else bayer]

    blank = np.zeros((framing.size[1], framing.size[0]), np.uint8)

    def convert() -> Iterator[tuple[DecodedFrame, np.ndarray | None, tuple[float, ...]]]:
        """Decode thread: demosaic, gray, crop, resize and the per-frame scores."""
        prev: np.ndarray | None = None  # previous decoded frame (frozen check)
        for f in frames:
            image = f.image
            if image is not None and image.ndim == 2 and image.dtype == np.uint8:
                if pattern[0] == "auto":
                    pattern[0] = detect_bayer(image)
                if pattern[0] is not None:
                    image = demosaic(image, pattern[0])
            gray = None if image is None else framing.apply(image)
            g = gray if gray is not None else blank
            yield f, gray, (*frame_scores(g), frame_diff(prev, g))
            prev = g

    tracker = FeatureTracker(window)
    flips = UpsideDownCheck()
    good: np.ndarray | None = None  # previous frame without a defect (tear reference)
    rows: list[tuple[float, ...]] = []
    small: list[np.ndarray] = []
    meta: list[tuple[int, float, str, bool, int]] = []
    bar = progress_bar(
        prefetch(convert()),
        total=info.expected_frames,
        unit="frame",
        desc="decode",
        file=progress_stream(),
        disable=None if progress else True,
        leave=False,
    )
    for f, gray, scores in bar:
        defect = 0
        if gray is not None:
            if torn_row(gray, good) is not None:
                defect = TORN
            elif flips.is_upside_down(gray):
                defect = UPSIDE_DOWN
        g = gray if gray is not None else blank
        tracker.update(g if gray is not None and defect == 0 else None)
        rows.append(scores)
        if gray is not None and defect == 0:
            good = gray
        small.append(g)
        meta.append((f.index, f.timestamp, f.name, gray is not None, defect))
    bar.close()
    table = np.array(rows, float).reshape(-1, len(SCORE_NAMES))
    tables: dict[str, np.ndarray] = {name: table[:, i] for i, name in enumerate(SCORE_NAMES)}
    tables["source_index"] = np.array([m[0] for m in meta], np.int64)
    tables["timestamp"] = np.array([m[1] for m in meta], float)
    tables["readable"] = np.array([m[3] for m in meta], bool)
    tables["defect"] = np.array([m[4] for m in meta], np.int8)
    tables["name"] = np.array([m[2] for m in meta])
    tables.update(tracker.tables())
    found = pattern[0] if pattern[0] != "auto" else None
    return small, tables, found


def _defects(sel: Selection) -> dict[str, np.ndarray]:
    """Decoded positions [K] of the frames dropped for each stream defect (K > 0 only)."""
    out = {}
    for name in ("torn", "upside_down", "frozen", "unreadable"):
        at = np.flatnonzero(sel.reason == REASONS.index(name))
        if len(at):
            out[name] = at
    return out


def _telemetry_tables(t: Telemetry, readable: np.ndarray) -> dict[str, np.ndarray]:
    """Per-decoded-frame telemetry tables; frame times replace the folder's assumed rate."""
    out = {
        "prior_c2w": t.prior_c2w,
        "prior_valid": t.prior_valid,
        "frame_id": t.frame_id,
        "camera_frame": t.camera_frame,
        "dropped_before": t.dropped_before,
    }
    if len(t.frame_time) == len(readable) and np.isfinite(t.frame_time).all():
        out["timestamp"] = t.frame_time
    return out


def _nothing_to_reconstruct(n: int, sel: Selection) -> str:
    counts = {k: v for k, v in sel.counts().items() if not k.startswith("kept")}
    worst = max(counts, key=counts.get) if counts else "redundant"  # type: ignore[arg-type]
    why = {
        "black": f"{counts.get('black', 0)} of {n} frames are black",
        "blank": f"{counts.get('blank', 0)} of {n} frames are blank (no texture)",
        "frozen": f"the video is frozen ({counts.get('frozen', 0)} of {n} frames repeat the last)",
        "clipped": f"{counts.get('clipped', 0)} of {n} frames are over/under-exposed",
        "blurry": f"{counts.get('blurry', 0)} of {n} frames are blurry",
        "unreadable": f"{counts.get('unreadable', 0)} of {n} images cannot be read",
    }.get(worst, f"only {int(sel.keep.sum())} of {n} frames is usable")
    return f"nothing to reconstruct: {why} (need at least {MIN_KEPT} usable frames)"


def params_record(params: IngestParams) -> dict[str, object]:
    """JSON-able parameters for provenance."""
    d = asdict(params)
    d["size"] = list(params.size)
    return d


__all__ = [
    "REASONS",
    "IngestParams",
    "IngestResult",
    "ingest",
    "params_record",
]
