"""Frame selection: which decoded frames to keep, and why every other one was dropped.

:func:`select_frames` works only from the per-frame score tables (see :mod:`.quality`), the
defect reasons (:mod:`.defects`) and the pair tables of the feature tracks (:mod:`.tracks`), so a
decision stored in ``frames.h5`` can be replayed with other thresholds without decoding again.

Rules, in order:

1. Defects and quality. A frame is dropped as ``unreadable``, a stream defect (``torn``,
   ``upside_down``: see :mod:`.defects`), ``black`` (mean < ``black_level``), ``blank``
   (contrast < ``blank_contrast``, less than ``min_detail`` of the frame textured, or fewer than
   ``min_corners`` corners: nothing to match), ``clipped`` (more than ``max_clipped`` of its
   pixels under/over-exposed AND its textured area below ``detail_ratio`` times that of its
   neighbours: exposure ate the subject; a saturated backdrop that every frame shares is not
   over-exposure), ``frozen`` (differs from the previous decoded frame by less than
   ``frozen_diff`` DN: a repeated buffer), or ``blurry`` (sharpness below ``blur_ratio`` times
   the median of the usable frames within ``blur_window`` frames).
2. Viewpoint change, from the tracks shared by the last kept frame ``k`` and a later frame
   ``j``: the view has changed enough once the tracks moved ``min_motion`` pixels (median), OR
   their parallax (motion a homography cannot explain: depth-dependent, what triangulation
   needs) reached ``min_parallax`` pixels, OR fewer than ``min_survival`` of k's tracks survive.
   These are the MOST change allowed between kept frames: the next kept frame is the sharpest
   of the last ``lookahead`` frames before that point that changed at least half as much, so
   kept frames are never further apart than the thresholds say (an already thinned sequence
   keeps nearly every frame). The others are ``redundant``.
3. Overlap. A kept frame shares at least ``min_overlap`` of the previous kept frame's tracks:
   the frames past that point are never candidates; when even the next usable frame shares
   less (a sudden view change), it is kept: the change is bridged as well as it can be.
4. Coverage. No two consecutive kept frames are more than ``max_gap`` source frames apart: when
   the view does not change enough in time, the sharpest usable frame of the last ``lookahead``
   frames before the gap limit is kept (reason ``kept_gap``). Only where no usable frame exists
   at all (e.g. a black stretch) can a gap be longer; such gaps are reported.
5. Target count. With ``target`` set, the three viewpoint thresholds are scaled together
   (bisection) so that the number kept is as close as possible to ``target`` without exceeding
   it; the gap rule wins when the two conflict.

Pairs without tracks (textureless frames) count as not moved; the gap rule covers them.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field

import numpy as np

# Reason codes stored for every decoded frame; kept frames have codes < 2.
REASONS = (
    "kept",  # 0: enough viewpoint change (or the first usable frame)
    "kept_gap",  # 1: kept so that no coverage gap exceeds max_gap
    "black",  # 2
    "blank",  # 3
    "clipped",  # 4
    "frozen",  # 5: repeats the previous frame (a stalled or duplicating stream)
    "blurry",  # 6
    "redundant",  # 7: too little viewpoint change since the last kept frame, or a sharper won
    "unreadable",  # 8: the source frame could not be decoded (image folders)
    "torn",  # 9: bottom part lost in transmission (black, gray or shifted rows)
    "upside_down",  # 10: rotated 180 degrees against its neighbours
)
(
    KEPT, KEPT_GAP, BLACK, BLANK, CLIPPED, FROZEN, BLURRY, REDUNDANT, UNREADABLE, TORN,
    UPSIDE_DOWN,
) = range(len(REASONS))  # fmt: skip
BAND = 0.5  # candidates for the next kept frame changed at least BAND of the most allowed


@dataclass
class SelectionParams:
    """Thresholds of the selection rules (see the module docstring). DN = 8-bit levels."""

    min_motion: float = field(
        default=8.0, metadata={"help": "most median track motion (pixels) between kept frames"}
    )
    min_parallax: float = field(
        default=0.5,
        metadata={"help": "most track parallax (pixels beyond a homography) between kept frames"},
    )
    min_survival: float = field(
        default=0.7, metadata={"help": "least fraction of tracks surviving between kept frames"}
    )
    min_overlap: float = field(
        default=0.5, metadata={"help": "fraction of tracks consecutive kept frames must share"}
    )
    max_gap: int = field(default=6, metadata={"help": "most source frames between two kept frames"})
    target: int | None = field(
        default=None, metadata={"help": "keep about this many frames (scales the view thresholds)"}
    )
    lookahead: int = field(
        default=4, metadata={"help": "frames over which the sharpest candidate is chosen"}
    )
    black_level: float = field(
        default=10.0, metadata={"help": "mean brightness (DN) below which a frame is black"}
    )
    blank_contrast: float = field(
        default=4.0, metadata={"help": "contrast (DN std) below which a frame is blank"}
    )
    min_detail: float = field(
        default=0.01, metadata={"help": "textured fraction of the frame below which it is blank"}
    )
    min_corners: float = field(
        default=20.0, metadata={"help": "FAST corners (CLAHE frame) below which a frame is blank"}
    )
    max_clipped: float = field(
        default=0.5, metadata={"help": "clipped fraction above which the subject is checked"}
    )
    detail_ratio: float = field(
        default=0.5,
        metadata={
            "help": "clipped frames with less texture than this times their neighbours' are dropped"
        },
    )
    frozen_diff: float = field(
        default=0.3,
        metadata={"help": "mean |difference| (DN) to the previous frame of a frozen frame"},
    )
    blur_ratio: float = field(
        default=0.75,
        metadata={"help": "sharpness below this fraction of the local median is blurry"},
    )
    blur_window: int = field(default=31, metadata={"help": "frames in the local sharpness median"})

    def replace(self, **changes: object) -> SelectionParams:
        """A copy with some fields changed (``None`` values are ignored)."""
        return dataclasses.replace(self, **{k: v for k, v in changes.items() if v is not None})

    def problems(self) -> list[str]:
        """Out-of-range values, as ``--flag: problem`` lines (empty when all are valid)."""
        out = []
        fractions = ("min_survival", "min_overlap", "min_detail", "max_clipped", "detail_ratio")
        for f in dataclasses.fields(self):
            v = getattr(self, f.name)
            flag = "--" + f.name.replace("_", "-")
            if v is None:
                continue
            if not math.isfinite(v):
                out.append(f"{flag}: must be a finite number, got {v}")
            elif f.name in ("max_gap", "target", "lookahead", "blur_window") and v < 1:
                out.append(f"{flag}: must be >= 1, got {v}")
            elif f.name in fractions and not 0 <= v <= 1:
                out.append(f"{flag}: must be between 0 and 1, got {v}")
            elif v < 0:
                out.append(f"{flag}: must be >= 0, got {v}")
        return out


@dataclass
class Selection:
    """Outcome of :func:`select_frames` for N decoded frames."""

    keep: np.ndarray  # bool [N]
    reason: np.ndarray  # int8 [N], index into REASONS
    min_motion: float  # the min_motion used (scaled when a target was given)
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
    defect = np.asarray(tables.get("defect", np.zeros(n, np.int8)), np.int8)
    diff = np.asarray(tables["frame_diff"], float)
    sharp = np.asarray(tables["sharpness"], float)
    detail = np.asarray(tables["detail"], float)
    clipped = np.asarray(tables["clipped"], float)
    reason[~readable] = UNREADABLE
    reason[(reason == KEPT) & (defect > 0)] = defect[(reason == KEPT) & (defect > 0)]
    checks = [
        (bright < p.black_level, BLACK),
        (
            (np.asarray(tables["contrast"], float) < p.blank_contrast)
            | (detail < p.min_detail)
            | (np.asarray(tables["corners"], float) < p.min_corners),
            BLANK,
        ),
        (np.nan_to_num(diff, nan=np.inf) < p.frozen_diff, FROZEN),
    ]
    for mask, code in checks:
        reason[(reason == KEPT) & mask] = code
    usable = reason == KEPT
    ref_detail = _local_median(np.where(usable, detail, np.nan), p.blur_window)
    reason[usable & (clipped > p.max_clipped) & (detail < p.detail_ratio * ref_detail)] = CLIPPED
    usable = reason == KEPT
    ref = _local_median(np.where(usable, sharp, np.nan), p.blur_window)
    reason[usable & (sharp < p.blur_ratio * ref)] = BLURRY
    return reason


def select_frames(
    tables: dict[str, np.ndarray], params: SelectionParams, available: np.ndarray | None = None
) -> Selection:
    """Decide which of N decoded frames to keep, from their tables alone.

    Args:
        tables: per-decoded-frame arrays [N] named as in :data:`.quality.SCORE_NAMES`, plus
            ``source_index`` (int64, frame number in the source), optionally ``readable`` (bool)
            and ``defect`` (int8 reason code, 0 = none), and the pair tables
            ``pair_survival``, ``pair_motion``, ``pair_parallax`` [N, W] of :mod:`.tracks`
            (entry ``[j, d - 1]`` describes frames ``j - d`` and ``j``).
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
        return _greedy(tables, quality, params, 1.0)
    lo, hi = 0.0, 1.0
    while int(_greedy(tables, quality, params, hi).keep.sum()) > params.target and hi < 1e4:
        lo, hi = hi, 4.0 * hi
    best = _greedy(tables, quality, params, hi)
    if int(best.keep.sum()) > params.target:
        return best  # even the widest spacing keeps more: max_gap decides
    for _ in range(40):
        mid = 0.5 * (lo + hi)
        sel = _greedy(tables, quality, params, mid)
        if int(sel.keep.sum()) <= params.target:
            best, hi = sel, mid
        else:
            lo = mid
        if hi - lo < 1e-4 * hi:
            break
    return best


def _change(
    tables: dict[str, np.ndarray], p: SelectionParams, scale: float, k: int, js: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """(change, survival) [len(js)] of frames ``js`` against frame ``k`` (k < js <= k + W).

    ``change`` is the largest of motion / min_motion, parallax / min_parallax and
    (1 - survival) / (1 - min_survival), each threshold times ``scale``: >= 1 means the view
    changed enough. Unknown measures (no shared tracks) count as no change; a zero threshold
    makes every measured frame a change.
    """
    d = js - k - 1
    values = np.stack(
        [
            np.asarray(tables["pair_motion"])[js, d],
            np.asarray(tables["pair_parallax"])[js, d],
            1.0 - np.asarray(tables["pair_survival"])[js, d],
        ]
    ).astype(float)
    limits = scale * np.array([p.min_motion, p.min_parallax, 1.0 - p.min_survival])[:, None]
    with np.errstate(divide="ignore", invalid="ignore"):
        parts = np.where(limits > 0, values / np.where(limits > 0, limits, 1.0), np.inf)
    parts = np.where(np.isnan(values), 0.0, parts)
    surv = np.nan_to_num(1.0 - values[2], nan=0.0)
    return parts.max(axis=0), surv


def _greedy(
    tables: dict[str, np.ndarray], quality: np.ndarray, p: SelectionParams, scale: float
) -> Selection:
    src = np.asarray(tables["source_index"], np.int64)
    window = np.asarray(tables["pair_motion"]).shape[1]
    sharp = np.asarray(tables["sharpness"], float)
    reason = quality.copy()
    cand = np.flatnonzero(quality == KEPT)
    keep = np.zeros(len(quality), bool)
    gaps: list[tuple[int, int]] = []
    used = scale * p.min_motion
    if len(cand) == 0:
        return Selection(keep, reason, used, gaps)
    reason[cand] = REDUNDANT
    # Start with the sharpest of the first frames that still show the first usable frame's view.
    near = cand[(src[cand] - src[cand[0]] < p.lookahead) & (cand - cand[0] <= window)]
    change, _ = _change(tables, p, scale, int(cand[0]), near[1:])
    first = near[: 1 + int(np.argmax(np.r_[change >= BAND, True]))]
    k = int(first[np.argmax(sharp[first])])
    keep[k], reason[k] = True, KEPT
    pos = int(np.searchsorted(cand, k)) + 1
    while pos < len(cand):
        later = cand[pos:]
        within = later[(src[later] - src[k] <= p.max_gap) & (later - k <= window)]
        change, surv = _change(tables, p, scale, k, within)
        over = np.flatnonzero((change >= 1.0) | (surv < p.min_overlap))
        if len(over):  # keep before the view has changed too much (never past it)
            j = int(over[0])
            pool = within[:j][change[:j] >= BAND][-p.lookahead :] if j else within[:1]
            pool = pool if len(pool) else within[j - 1 : j]
            code = KEPT
        elif len(within) == len(later):
            break  # the rest of the flight is within max_gap of the last kept frame
        elif len(within):
            limit = src[k] + p.max_gap
            pool = within[src[within] > limit - p.lookahead]
            if len(pool) == 0:
                pool = within[-1:]
            code = KEPT_GAP
        else:  # nothing usable within max_gap: the gap is unavoidable
            pool = later[:1]
            gaps.append((int(src[k]), int(src[pool[0]])))
            code = KEPT_GAP
        k = int(pool[len(pool) - 1 - np.argmax(sharp[pool][::-1])])  # sharpest; ties: latest
        keep[k], reason[k] = True, code
        pos = int(np.searchsorted(cand, k)) + 1
    return Selection(keep, reason, used, gaps)


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
