"""The ingest stage: decode a flight, convert every frame to small gray, score it, select frames.

:func:`ingest` returns an :class:`IngestResult` (kept images, per-decoded-frame tables, the
decision and a summary) and never writes files; the ``dronecap ingest`` command stores the result
as ``frames.h5``. Every decoded frame is converted (gray, crop, area resize) in a background
thread while the main thread scores it, so decoding overlaps with scoring on two cores.
"""

from __future__ import annotations

import time
from collections.abc import Iterator
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from dronecap.camera import Camera
from dronecap.camera.files import load_camera
from dronecap.capture.decode import DecodedFrame, SourceInfo, open_source, prefetch, progress_stream
from dronecap.capture.framing import LUMA_WEIGHTS, Framing, make_framing
from dronecap.capture.quality import SCORE_NAMES, MotionTracker, frame_scores
from dronecap.capture.selection import (
    REASONS,
    Selection,
    SelectionParams,
    select_frames,
)
from dronecap.errors import InputError

MIN_KEPT = 2  # fewer kept frames leave nothing to reconstruct


@dataclass
class IngestParams:
    """Options of the ingest stage (the CLI's flags)."""

    size: tuple[int, int] = (160, 160)  # output (width, height) in pixels
    crop: str = "center"  # "center", "stretch" or "X,Y,W,H" (see framing.make_framing)
    fps: float = 30.0  # frame rate assumed for an image folder
    intrinsics: str | None = None  # "fx,fy,cx,cy" or a calibration file (camera.files); None
    allow_truncated: bool = False  # keep what decodes from a truncated video
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
            "crop_box": list(self.framing.box),
            "size": list(self.framing.size),
            "luma_weights": LUMA_WEIGHTS,
            "run_fps": n / max(self.seconds, 1e-9),
            "warnings": self.warnings,
        }

    def summary_line(self) -> str:
        """One line: decoded, kept, dropped by reason, speed of the run."""
        s = self.summary()
        dropped = ", ".join(f"{k} {v}" for k, v in s["dropped"].items()) or "none"  # type: ignore[union-attr]
        return (
            f"decoded {s['decoded']} frames, kept {s['kept']}, dropped: {dropped}"
            f" ({s['run_fps']:.0f} frames/s)"
        )


def ingest(source: str | Path, params: IngestParams, progress: bool = True) -> IngestResult:
    """Decode ``source`` (video file or image folder), score every frame and select frames.

    Raises:
        InputError: missing/unreadable source, no decodable frame, a truncated video (unless
            ``params.allow_truncated``), or fewer than two usable frames (nothing to
            reconstruct: black, blank or frozen footage).
    """
    t0 = time.perf_counter()
    src = open_source(source, params.fps)
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

    small, tables = _decode_and_score(src.frames(), framing, info, progress)
    n = len(small)
    if n == 0:
        raise InputError("no decodable frames (empty or damaged video stream)", info.path)
    expected = info.expected_frames
    if info.kind == "video" and expected is not None and n < expected - 1:
        msg = f"truncated: decoded {n} of {expected} frames ({100 * n / expected:.0f}%)"
        if not params.allow_truncated:
            raise InputError(f"{msg}; pass --allow-truncated to ingest those {n}", info.path)
        warnings.append(msg)

    if n == 1:
        raise InputError(
            "only one decodable frame: a single view has nothing to reconstruct", info.path
        )
    selection = select_frames(tables, params.selection)
    kept = np.flatnonzero(selection.keep)
    if len(kept) < MIN_KEPT:
        raise InputError(_nothing_to_reconstruct(n, selection), info.path)
    if selection.gaps:
        warnings.append(
            "coverage gaps with no usable frame: "
            + ", ".join(f"frames {a}-{b}" for a, b in selection.gaps)
        )
    images = np.stack([small[i] for i in kept])[..., None]
    names = [tables["name"][i] for i in kept]
    return IngestResult(
        info=info,
        framing=framing,
        camera=camera,
        camera_source=camera_source,
        images=images,
        names=names,
        tables={k: v for k, v in tables.items() if k != "name"},
        selection=selection,
        warnings=warnings,
        seconds=time.perf_counter() - t0,
    )


def _decode_and_score(
    frames: Iterator[DecodedFrame], framing: Framing, info: SourceInfo, progress: bool
) -> tuple[list[np.ndarray], dict[str, np.ndarray]]:
    """Convert and score every frame; returns the small frames and the tables [N]."""
    from dronecap.progress import progress_bar

    def convert() -> Iterator[tuple[DecodedFrame, np.ndarray | None]]:
        for f in frames:
            yield f, None if f.image is None else framing.apply(f.image)

    blank = np.zeros((framing.size[1], framing.size[0]), np.uint8)
    tracker = MotionTracker()
    rows: list[tuple[float, ...]] = []
    small: list[np.ndarray] = []
    meta: list[tuple[int, float, str, bool]] = []
    bar = progress_bar(
        prefetch(convert()),
        total=info.expected_frames,
        unit="frame",
        desc="decode",
        file=progress_stream(),
        disable=None if progress else True,
        leave=False,
    )
    for f, gray in bar:
        readable = gray is not None
        g = gray if readable else blank
        motion, diff = tracker.update(g)
        rows.append((*frame_scores(g), diff, motion))
        small.append(g)
        meta.append((f.index, f.timestamp, f.name, readable))
    bar.close()
    scores = np.array(rows, float).reshape(-1, len(SCORE_NAMES))
    tables: dict[str, np.ndarray] = {name: scores[:, i] for i, name in enumerate(SCORE_NAMES)}
    tables["source_index"] = np.array([m[0] for m in meta], np.int64)
    tables["timestamp"] = np.array([m[1] for m in meta], float)
    tables["readable"] = np.array([m[3] for m in meta], bool)
    tables["name"] = np.array([m[2] for m in meta])
    return small, tables


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


# Per-decoded-frame tables as stored under /extra in frames.h5 (table name -> extra name).
EXTRA_NAMES = {name: name for name in SCORE_NAMES} | {
    "source_index": "decoded_source_index",
    "timestamp": "decoded_timestamp",
    "readable": "readable",
}


def tables_to_extra(tables: dict[str, np.ndarray], sel: Selection) -> dict[str, np.ndarray]:
    """The arrays stored under ``/extra``: every table [N], ``keep`` uint8 [N], ``reason``
    int8 [N] and ``reason_legend`` str [len(REASONS)] (code -> name)."""
    extra = {EXTRA_NAMES[k]: np.asarray(v) for k, v in tables.items() if k in EXTRA_NAMES}
    extra["readable"] = extra["readable"].astype(np.uint8)
    extra["keep"] = sel.keep.astype(np.uint8)
    extra["reason"] = sel.reason.astype(np.int8)
    extra["reason_legend"] = np.array(REASONS)
    return extra


def extra_to_tables(extra: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """Inverse of :func:`tables_to_extra` for the score tables (what select_frames reads)."""
    missing = [v for v in EXTRA_NAMES.values() if v not in extra]
    if missing:
        raise InputError(f"has no ingest score tables to replay (missing {', '.join(missing)})")
    return {k: np.asarray(extra[v]) for k, v in EXTRA_NAMES.items()}


def params_record(params: IngestParams) -> dict[str, object]:
    """JSON-able parameters for provenance."""
    d = asdict(params)
    d["size"] = list(params.size)
    return d


__all__ = [
    "REASONS",
    "IngestParams",
    "IngestResult",
    "extra_to_tables",
    "ingest",
    "params_record",
    "tables_to_extra",
]
