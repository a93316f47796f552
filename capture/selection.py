"""Frame selection: which decoded frames to keep, and why every other one was dropped.

:func:`select_frames` works only from the per-frame score tables (see :mod:`.quality`), so a
decision stored in ``frames.h5`` can be replayed with other thresholds without decoding again.

Rules, in order:

1. Quality. A frame is dropped as ``black`` (mean < ``black_level``), ``blank`` (contrast <
   ``blank_contrast``: nothing to match), ``clipped`` (more than ``max_clipped`` of its pixels
   under/over-exposed), ``frozen`` (differs from the previous decoded frame by less than
   ``frozen_diff`` DN: a repeated frame), or ``blurry`` (sharpness below ``blur_ratio`` times the
   median sharpness of the usable frames within ``blur_window`` frames: blur is judged against
   neighbours that see similar texture).
2. Viewpoint change. Walking forward from the last kept frame, motion accumulates (the sum of
   the per-frame feature displacements, steps under ``motion_floor`` pixels counting as zero).
   Once it reaches ``min_motion`` pixels, the sharpest usable frame among those that reached it
   within the next ``lookahead`` frames (and within half ``min_motion`` more motion) is kept:
   a sharp frame beats its blurred twin, and a hovering drone (tiny motion) yields few frames.
   The others are ``redundant``.
3. Coverage. No two consecutive kept frames are more than ``max_gap`` source frames apart: when
   motion does not reach ``min_motion`` in time, the sharpest usable frame of the last
   ``lookahead`` frames before the gap limit is kept (reason ``kept_gap``). Only where no usable
   frame exists at all (e.g. a black stretch) can a gap be longer; such gaps are reported.
4. Target count. With ``target`` set, ``min_motion`` is searched (bisection) so that the number
   kept is as close as possible to ``target`` without exceeding it; the gap rule wins when the
   two conflict.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

import numpy as np

# Reason codes stored for every decoded frame; kept frames have codes < 2.
REASONS = (
    "kept",  # 0: enough viewpoint change (or the first usable frame)
    "kept_gap",  # 1: kept so that no coverage gap exceeds max_gap
    "black",  # 2
    "blank",  # 3
    "clipped",  # 4
    "frozen",  # 5
    "blurry",  # 6
    "redundant",  # 7: too little motion since the last kept frame, or a sharper neighbour won
    "unreadable",  # 8: the source frame could not be decoded (image folders)
)
KEPT, KEPT_GAP, BLACK, BLANK, CLIPPED, FROZEN, BLURRY, REDUNDANT, UNREADABLE = range(len(REASONS))


@dataclass
class SelectionParams:
    """Thresholds of the selection rules (see the module docstring). DN = 8-bit levels."""

    min_motion: float = field(
        default=4.0,
        metadata={"help": "pixels of viewpoint change between kept frames (output frame)"},
    )
    max_gap: int = field(default=6, metadata={"help": "most source frames between two kept frames"})
    target: int | None = field(
        default=None,
        metadata={"help": "keep about this many frames (searches min_motion); None: off"},
    )
    lookahead: int = field(
        default=4, metadata={"help": "frames over which the sharpest candidate is chosen"}
    )
    motion_floor: float = field(
        default=0.15,
        metadata={"help": "per-frame motion (pixels) below this counts as none (jitter)"},
    )
    black_level: float = field(
        default=10.0, metadata={"help": "mean brightness (DN) below which a frame is black"}
    )
    blank_contrast: float = field(
        default=4.0, metadata={"help": "contrast (DN std) below which a frame is blank"}
    )
    max_clipped: float = field(default=0.5, metadata={"help": "largest fraction of clipped pixels"})
    frozen_diff: float = field(
        default=0.3,
        metadata={"help": "mean |difference| (DN) to the previous frame of a frozen frame"},
    )
    blur_ratio: float = field(
        default=0.6,
        metadata={"help": "sharpness below this fraction of the local median is blurry"},
    )
    blur_window: int = field(default=31, metadata={"help": "frames in the local sharpness median"})

    def replace(self, **changes: object) -> SelectionParams:
        """A copy with some fields changed (``None`` values are ignored)."""
        return dataclasses.replace(self, **{k: v for k, v in changes.items() if v is not None})


@dataclass
class Selection:
    """Outcome of :func:`select_frames` for N decoded frames."""

    keep: np.ndarray  # bool [N]
    reason: np.ndarray  # int8 [N], index into REASONS
    min_motion: float  # the min_motion used (searched when a target was given)
    gaps: list[tuple[int, int]] = field(default_factory=list)  # kept pairs further than max_gap

    def counts(self) -> dict[str, int]:
        """Number of frames per reason, for every reason that occurs."""
        values, counts = np.unique(self.reason, return_counts=True)
        return {REASONS[int(v)]: int(c) for v, c in zip(values, counts, strict=True)}


def quality_reasons(tables: dict[str, np.ndarray], p: SelectionParams) -> np.ndarray:
    """Rule 1 alone: int8 [N] with KEPT for usable frames, else the first failing reason."""
    bright = np.asarray(tables["brightness"], float)
    n = len(bright)
    reason = np.full(n, KEPT, np.int8)
    readable = np.asarray(tables.get("readable", np.ones(n, bool)), bool)
    diff = np.asarray(tables["frame_diff"], float)
    sharp = np.asarray(tables["sharpness"], float)
    checks = [
        (~readable, UNREADABLE),
        (bright < p.black_level, BLACK),
        (np.asarray(tables["contrast"], float) < p.blank_contrast, BLANK),
        (np.asarray(tables["clipped"], float) > p.max_clipped, CLIPPED),
        (np.nan_to_num(diff, nan=np.inf) < p.frozen_diff, FROZEN),
    ]
    for mask, code in checks:
        reason[(reason == KEPT) & mask] = code
    usable = reason == KEPT
    ref = _local_median(np.where(usable, sharp, np.nan), p.blur_window)
    reason[usable & (sharp < p.blur_ratio * ref)] = BLURRY
    return reason


def select_frames(
    tables: dict[str, np.ndarray], params: SelectionParams, available: np.ndarray | None = None
) -> Selection:
    """Decide which of N decoded frames to keep, from their score tables alone.

    Args:
        tables: per-decoded-frame arrays [N] named as in :data:`.quality.SCORE_NAMES`
            (``motion`` in pixels from the previous decoded frame, NaN when unknown) plus
            ``source_index`` (int64, frame number in the source) and optionally ``readable``.
        params: the thresholds.
        available: optional bool [N]; frames outside it are never kept (e.g. replaying a stored
            selection among the frames whose images were stored). Default: all.

    Returns:
        a :class:`Selection` with the keep mask and a reason code for every frame.
    """
    quality = quality_reasons(tables, params)
    if available is not None:
        quality[(quality == KEPT) & ~np.asarray(available, bool)] = REDUNDANT
    if params.target is None:
        return _greedy(tables, quality, params)
    lo, hi = 0.0, float(np.nansum(np.asarray(tables["motion"], float))) + 1.0
    best = _greedy(tables, quality, params.replace(min_motion=hi))
    if int(best.keep.sum()) > params.target:
        return best  # even the largest spacing keeps more: max_gap decides
    for _ in range(40):
        mid = 0.5 * (lo + hi)
        sel = _greedy(tables, quality, params.replace(min_motion=mid))
        if int(sel.keep.sum()) <= params.target:
            best, hi = sel, mid
        else:
            lo = mid
        if hi - lo < 1e-3:
            break
    return best


def _greedy(tables: dict[str, np.ndarray], quality: np.ndarray, p: SelectionParams) -> Selection:
    src = np.asarray(tables["source_index"], np.int64)
    step = np.nan_to_num(np.asarray(tables["motion"], float), nan=0.0)
    step[step < p.motion_floor] = 0.0
    travel = np.cumsum(step)  # motion accumulated from the first frame to frame i
    sharp = np.asarray(tables["sharpness"], float)
    reason = quality.copy()
    cand = np.flatnonzero(quality == KEPT)
    keep = np.zeros(len(quality), bool)
    gaps: list[tuple[int, int]] = []
    if len(cand) == 0:
        return Selection(keep, reason, p.min_motion, gaps)
    reason[cand] = REDUNDANT
    # Start with the sharpest usable frame before the camera has moved min_motion (the first
    # usable frame itself always qualifies, so min_motion = 0 keeps every usable frame).
    early = (travel[cand] - travel[cand[0]] < p.min_motion) & (
        src[cand] - src[cand[0]] <= p.max_gap
    )
    early[0] = True
    first = cand[early]
    k = int(first[np.argmax(sharp[first])])
    keep[k], reason[k] = True, KEPT
    pos = int(np.searchsorted(cand, k)) + 1
    while pos < len(cand):
        later = cand[pos:]
        within = later[src[later] - src[k] <= p.max_gap]
        moved = within[travel[within] - travel[k] >= p.min_motion]
        if len(moved):
            j0 = moved[0]
            close = (src[moved] - src[j0] < p.lookahead) & (
                travel[moved] - travel[j0] <= 0.5 * p.min_motion
            )
            pool = moved[close]
            code = KEPT
        elif len(within) == len(later):
            break  # the rest of the flight is within max_gap of the last kept frame
        elif len(within):
            pool = within[src[within] > src[k] + p.max_gap - p.lookahead]
            if len(pool) == 0:
                pool = within[-1:]
            code = KEPT_GAP
        else:  # nothing usable within max_gap: the gap is unavoidable
            pool = later[:1]
            gaps.append((int(src[k]), int(src[pool[0]])))
            code = KEPT_GAP
        k = int(pool[np.argmax(sharp[pool])])
        keep[k], reason[k] = True, code
        pos = int(np.searchsorted(cand, k)) + 1
    return Selection(keep, reason, p.min_motion, gaps)


def _local_median(x: np.ndarray, window: int) -> np.ndarray:
    """Median of the finite values of ``x`` [N] within ``window`` frames around each frame."""
    n = len(x)
    half = max(window, 1) // 2
    padded = np.concatenate([np.full(half, np.nan), x, np.full(half, np.nan)])
    windows = np.lib.stride_tricks.sliding_window_view(padded, 2 * half + 1)[:n]
    out = np.full(n, np.nan)
    has = np.isfinite(windows).any(axis=1)
    if has.any():
        out[has] = np.nanmedian(windows[has], axis=1)
    return out
