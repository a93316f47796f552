"""Our choice of the pair of frames COLMAP's incremental mapper starts from.

Among verified pairs with a general epipolar geometry a few frames apart, the ones with most
inliers get their triangulation angle and forward motion measured; :func:`rank_initial_pairs`
orders the candidates to try (:func:`dronecap.sfm.colmap_steps.map_from_pairs`). Slow flights
whose pairs are all labelled planar fall back to the widest planar pairs. Why not COLMAP's own
choice: see :func:`initial_pairs`.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

from dronecap.sfm.options import SfmOptions

GENERAL_CONFIGS = ("CALIBRATED", "UNCALIBRATED")  # two-view geometries with parallax
INIT_CANDIDATES = 30  # pairs (most inliers first) whose triangulation angle is measured per tier
FALLBACK_MIN_ANGLE = 1.0  # deg: below this a pair is a near-duplicate view, never a start
WIDEST_GAP_DIVISOR = 4  # the initial pair's gap widens up to frames / 4 (loop twins lie ~N/2 apart)


class PairCandidate(NamedTuple):
    """A measured initial-pair candidate: two database image ids and their two-view geometry."""

    inliers: int  # verified matches
    angle: float  # median triangulation angle, deg (0 when the two-view pose failed)
    forward: float  # |z| of the unit relative translation: 1 is straight along the view
    a: int
    b: int


def initial_pairs(
    database: Path, opts: SfmOptions, min_gap: int = 3
) -> tuple[list[tuple[tuple[int, int], dict[str, Any]]], dict[str, Any]]:
    """Our initial pairs, best first, each as (database image ids, report record: names,
    inliers, angle, forward motion), empty to leave the choice to COLMAP; plus a description of
    the search for the report (candidates, measured, max_gap).

    Among verified pairs whose two-view geometry is a general epipolar one (CALIBRATED or
    UNCALIBRATED, not PLANAR / PANORAMIC) and that lie ``min_gap`` to ``opts.init_max_gap``
    frames apart in flight order, the :data:`INIT_CANDIDATES` with most inliers get their median
    triangulation angle and forward motion measured (COLMAP's relative pose from the database's
    geometry); the gap widens while no pair COLMAP accepts has both ``opts.init_min_num_inliers``
    and ``opts.init_min_tri_angle``. :func:`rank_initial_pairs` orders them.

    Why: COLMAP's own choice favours the pair with the most matches anywhere. On small frames
    looking at a wall most pairs are labelled planar, and a start from one of them takes its
    relative pose from an ambiguous homography decomposition (simulated corridor: ATE 10-17 %,
    see docs/sfm.md). A near-duplicate view has no triangulation angle, and a loop-closure twin
    (the same view on two passes of an orbit) is far apart in the flight: from either the model
    never grows past a few frames.
    """
    import pycolmap

    general = {int(getattr(pycolmap.TwoViewGeometryConfiguration, c)) for c in GENERAL_CONFIGS}
    with pycolmap.Database.open(database) as db:
        images = {im.image_id: im for im in db.read_all_images()}
        pair_ids, geoms = db.read_two_view_geometries()
        rank = {i: r for r, i in enumerate(sorted(images, key=lambda i: images[i].name))}
        general_pairs = []
        for pair_id, g in zip(pair_ids, geoms, strict=True):
            a, b = pycolmap.pair_id_to_image_pair(pair_id)
            gap = abs(rank[a] - rank[b])
            if int(g.config) in general and gap >= min_gap:
                general_pairs.append((g.inlier_matches.shape[0], gap, a, b, g))
        general_pairs.sort(key=lambda c: -c[0])
        measured: list[PairCandidate] = []
        done: set[tuple[int, int]] = set()
        max_gap = opts.init_max_gap
        widest = max(opts.init_max_gap, len(images) // WIDEST_GAP_DIVISOR)
        while True:  # widen the gap until a strong pair is found (dense selections)
            tier = [c for c in general_pairs if c[1] <= max_gap and (c[2], c[3]) not in done]
            for n, _, a, b, g in tier[:INIT_CANDIDATES]:
                done.add((a, b))
                measured.append(_measure_pair(db, images, n, a, b, g))
            if max_gap >= widest or any(_accepted(c, opts) and _strong(c, opts) for c in measured):
                break
            max_gap = min(2 * max_gap, widest)
        planar = not any(_accepted(c, opts) for c in measured)
        if planar:  # a slow flight: every pair within the sequential overlap looks planar
            measured = _measure_planar(db, images, (pair_ids, geoms), rank, opts, min_gap, widest)
        ranked = rank_initial_pairs(measured, opts)
    info = {
        "candidates": len(general_pairs),
        "measured": len(measured),
        "max_gap": max_gap,
        "planar_fallback": planar,
    }
    return [((c.a, c.b), _describe_pair(c, images)) for c in ranked], info


def _measure_planar(
    db: Any,
    images: dict[int, Any],
    pairs: tuple[Any, list[Any]],
    rank: dict[int, int],
    opts: SfmOptions,
    min_gap: int,
    widest: int,
) -> list[PairCandidate]:
    """Measure planar / panoramic pairs (``pairs``: the database's pair ids and geometries)
    ``min_gap`` to ``opts.init_max_gap`` frames apart, the widest gap first (most inliers among
    equals): the fallback when no general epipolar pair is a start COLMAP accepts. While none
    of them is accepted (near-duplicate views of a dense selection), the gap doubles up to
    ``widest`` frames.

    Why: in a slow flight (the 1954-frame corridor, 446 kept frames) all 4495 verified pairs
    are labelled planar-or-panoramic, so :func:`initial_pairs` has no candidate and COLMAP's
    own search ran for 1116 s and built a bent model (ATE 2.9 %); the widest pair, 10 frames
    apart at a 3 deg triangulation angle, starts a straight model (ATE 0.21 %). On the
    3901-kept-frame flight at SIFT threshold 0.01 no pair 10 frames apart was accepted.
    """
    pool = []
    for pair_id, g in zip(*pairs, strict=True):
        a, b = _pair_images(pair_id)
        gap = abs(rank[a] - rank[b])
        if min_gap <= gap <= widest and g.inlier_matches.shape[0] > 0:
            pool.append((gap, g.inlier_matches.shape[0], a, b, g))
    pool.sort(key=lambda c: (-c[0], -c[1]))
    measured: list[PairCandidate] = []
    max_gap = opts.init_max_gap
    while True:
        tier = [c for c in pool if c[0] <= max_gap][:INIT_CANDIDATES]
        measured = [_measure_pair(db, images, n, a, b, g) for _, n, a, b, g in tier]
        if max_gap >= widest or any(_accepted(c, opts) for c in measured):
            return measured
        max_gap = min(2 * max_gap, widest)


def _pair_images(pair_id: int) -> tuple[int, int]:
    """The two database image ids of a COLMAP pair id."""
    import pycolmap

    a, b = pycolmap.pair_id_to_image_pair(pair_id)
    return int(a), int(b)


def _measure_pair(db: Any, images: dict[int, Any], n: int, a: int, b: int, g: Any) -> PairCandidate:
    """Relative pose of pair (a, b) from its stored geometry ``g``: angle and forward motion."""
    import pycolmap

    cam_a = db.read_camera(images[a].camera_id)
    cam_b = db.read_camera(images[b].camera_id)
    kp_a = np.asarray(db.read_keypoints(a))[:, :2].astype(np.float64)
    kp_b = np.asarray(db.read_keypoints(b))[:, :2].astype(np.float64)
    ok = pycolmap.estimate_two_view_geometry_pose(cam_a, kp_a, cam_b, kp_b, g)
    if not ok or g.tri_angle < 0:
        return PairCandidate(n, 0.0, 1.0, a, b)
    t = np.asarray(g.cam2_from_cam1.translation, dtype=np.float64)
    forward = float(abs(t[2]) / max(np.linalg.norm(t), 1e-12))
    return PairCandidate(n, float(np.degrees(g.tri_angle)), forward, a, b)


def _describe_pair(c: PairCandidate, images: dict[int, Any]) -> dict[str, Any]:
    """The report's record of an initial pair."""
    return {
        "frames": [images[c.a].name, images[c.b].name],
        "inliers": c.inliers,
        "tri_angle_deg": round(c.angle, 2),
        "forward_motion": round(c.forward, 3),
    }


def _accepted(c: PairCandidate, opts: SfmOptions) -> bool:
    """Whether COLMAP's mapper can start from ``c``: not straight along the view (forward motion
    at most ``opts.init_max_forward_motion``) and no near-duplicate view."""
    return c.forward <= opts.init_max_forward_motion and c.angle >= FALLBACK_MIN_ANGLE


def _strong(c: PairCandidate, opts: SfmOptions) -> bool:
    """Whether ``c`` has the inliers and the angle asked of an initial pair."""
    return c.inliers >= opts.init_min_num_inliers and c.angle >= opts.init_min_tri_angle


def rank_initial_pairs(measured: list[PairCandidate], opts: SfmOptions) -> list[PairCandidate]:
    """The candidates to start mapping from, in the order to try them.

    Only pairs COLMAP's mapper accepts as a start (:func:`_accepted`). When some have at least
    ``opts.init_min_num_inliers``, only those are offered: the ones that also reach
    ``opts.init_min_tri_angle`` first (most inliers first), then the others (widest angle
    first). Pairs with fewer inliers are offered, in the same order, only when no pair has
    enough: their relative pose, and the angle measured from it, is unreliable (simulated aideck
    corridor: a 25-inlier pair measured at 3.6-16 deg over runs on the same frames started a
    model bent by 90 deg, ATE 9.5-12.6 %, where every accepted pair with 29+ inliers on the same
    matches gave 0.11-0.13 %).
    """
    usable = [c for c in measured if _accepted(c, opts)]
    enough = [c for c in usable if c.inliers >= opts.init_min_num_inliers]
    pool = enough or usable
    wide = [c for c in pool if c.angle >= opts.init_min_tri_angle]
    narrow = [c for c in pool if c.angle < opts.init_min_tri_angle]
    return sorted(wide, key=lambda c: (-c.inliers, -c.angle)) + sorted(
        narrow, key=lambda c: (-c.angle, -c.inliers)
    )
