"""Initial pairs for a dense flight: a few wide pairs matched on purpose when the flight's own
pairs are all too close for a start.

Sequential matching pairs each frame with its next ``overlap`` frames. On a slow, dense flight
those are near-duplicate views: the 3901-kept-frame corridor (``simulate --frames 17500``) had
no general epipolar pair at all at SIFT contrast 0.01, and the widest planar pairs (20 frames
apart, 1.3 deg) were refused by COLMAP's mapper one after another (2 minutes per attempt in
the start chunk, then COLMAP's own search). Here, when no candidate reaches half the initial
triangulation angle, anchors spread over the frames the start may use are matched with the
frames :data:`WIDE_GAPS` later, verified with the essential matrix first (a pair is called
planar only when a homography explains strictly more, as for the global mapper), and the
search runs again with those pairs in the database.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

from dronecap.sfm.colmap_steps import match_listed
from dronecap.sfm.flights import flight_of
from dronecap.sfm.initial_pair import initial_pairs
from dronecap.sfm.options import SfmOptions

WIDE_GAPS = (16, 32, 64, 128)  # frames between an anchor and its partners (within a chunk)
WIDE_ANCHORS = 8  # anchors spread evenly over the frames the start may use


def wide_pairs(frames: list[str]) -> list[tuple[str, str]]:
    """Pairs of ``frames`` (flight order): :data:`WIDE_ANCHORS` anchors spread over the frames
    that have a partner :data:`WIDE_GAPS` [0] later, each with the frames every gap later that
    exist and belong to the same drone's flight (a swarm's names run flight after flight)."""
    room = len(frames) - WIDE_GAPS[0]
    if room <= 0:
        return []
    anchors = sorted(
        {round(i * (room - 1) / max(1, WIDE_ANCHORS - 1)) for i in range(WIDE_ANCHORS)}
    )
    return [
        (frames[a], frames[a + g])
        for a in anchors
        for g in WIDE_GAPS
        if a + g < len(frames) and flight_of(frames[a]) == flight_of(frames[a + g])
    ]


def start_pairs(
    database: Path, work: Path, opts: SfmOptions, frames: list[str]
) -> tuple[list[tuple[tuple[int, int], dict[str, Any]]], dict[str, Any]]:
    """:func:`~dronecap.sfm.initial_pair.initial_pairs` of ``database``; when none of them
    reaches half of ``opts.init_min_tri_angle``, the :func:`wide_pairs` of ``frames`` (the
    start chunk's, or the flight's) are matched into the database (pair list in ``work``) and
    the search runs again. The search record gets ``wide_pairs``: the pairs matched (0: none
    needed)."""
    pairs, info = initial_pairs(database, opts)
    if any(p[1]["tri_angle_deg"] >= opts.init_min_tri_angle / 2 for p in pairs):
        return pairs, {**info, "wide_pairs": 0}
    wanted = wide_pairs(frames)
    if not wanted:
        return pairs, {**info, "wide_pairs": 0}
    pair_file = work / "wide_pairs.txt"
    pair_file.write_text("".join(f"{a} {b}\n" for a, b in wanted))
    essential_first = dataclasses.replace(opts, max_h_inlier_ratio=opts.global_max_h_inlier_ratio)
    match_listed(database, pair_file, essential_first)
    pairs, info = initial_pairs(database, opts)
    return pairs, {**info, "wide_pairs": len(wanted)}
