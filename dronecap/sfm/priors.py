"""Telemetry pose priors: bring an SfM result into metres with gravity-aligned up.

Ingest stores, per kept frame, ``extra/prior_c2w`` (float64 [N, 4, 4], OpenCV camera axes,
metres, world z up) and ``extra/prior_valid`` (bool [N]) when the capture came with onboard
state (docs/capture.md, the telemetry contract). SfM recovers poses up to a similarity; this
module fits that similarity (COLMAP frame -> prior world) and says how well priors and recovered
poses agree.

The fit: Umeyama on camera centres with two rounds of trimming (frames whose residual exceeds
:data:`TRIM_FACTOR` x the median are dropped: a glitch or a drifting stretch of telemetry does not
pull the whole model). When the centres are (nearly) collinear — a straight forward flight — the
rotation about the flight line is not fixed by positions, so the rotation comes from the prior
orientations instead (chordal mean of R_prior R_sfm^T over the kept frames) and only scale and
shift from the centres. The pycolmap 4.2 mapper can use position priors inside bundle adjustment
(``use_prior_position``); we align after mapping instead, so a biased or drifting estimator
never bends the reconstruction.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from dronecap.datasets.format import Dataset
from dronecap.sfm.align import DegenerateAlignment, Similarity, rotation_angle_deg, umeyama

TRIM_FACTOR = 3.0  # residuals above this x the median are outliers (refit without them)
# A swarm: the drones' telemetry is taken to share one frame unless one similarity for all of
# them leaves this many times the residual of a similarity per drone (and over SHARED_MIN_M).
SHARED_FACTOR = 3.0
SHARED_MIN_M = 0.05
MIN_SPREAD = 0.05  # second/first singular value of the centres below this: use orientations
MIN_PRIORS = 3  # registered frames with a valid prior needed for a fit


@dataclass
class PriorFit:
    """The similarity from the SfM frame to the priors' metric world, and the agreement."""

    sim: Similarity  # x_world = sim(x_sfm), metres, z up
    used: np.ndarray  # bool [R]: registered frames whose priors counted in the final fit
    method: str  # "positions" (Umeyama) or "orientations+positions" (collinear centres)

    def agreement(self, c2w_sfm: np.ndarray, prior_c2w: np.ndarray) -> dict[str, float]:
        """Position and rotation differences (metres, degrees) between the aligned recovered
        poses [R, 4, 4] and their priors [R, 4, 4]."""
        aligned = self.sim.apply_poses(c2w_sfm)
        d = np.linalg.norm(aligned[:, :3, 3] - prior_c2w[:, :3, 3], axis=1)
        rel = np.einsum("nji,njk->nik", prior_c2w[:, :3, :3], aligned[:, :3, :3])
        rot = rotation_angle_deg(rel)
        return {
            "position_rmse_m": float(np.sqrt((d**2).mean())),
            "position_median_m": float(np.median(d)),
            "rotation_median_deg": float(np.median(rot)),
            "rotation_max_deg": float(rot.max()),
        }


def read_priors(ds: Dataset) -> tuple[np.ndarray, np.ndarray] | None:
    """(prior_c2w [N, 4, 4], prior_valid bool [N]) from frames.h5 extras, or None when absent,
    malformed or all invalid."""
    c2w, valid = ds.extra.get("prior_c2w"), ds.extra.get("prior_valid")
    if c2w is None or valid is None:
        return None
    c2w, valid = np.asarray(c2w, np.float64), np.asarray(valid, bool)
    if c2w.shape != (ds.n, 4, 4) or valid.shape != (ds.n,):
        return None
    valid = valid & np.isfinite(c2w).all(axis=(1, 2))
    return (c2w, valid) if valid.any() else None


def fit_to_priors(c2w_sfm: np.ndarray, prior_c2w: np.ndarray) -> PriorFit:
    """Similarity taking recovered poses [R, 4, 4] (SfM units) onto their priors [R, 4, 4].

    Raises:
        DegenerateAlignment: fewer than :data:`MIN_PRIORS` frames, or coincident centres.
    """
    if len(c2w_sfm) < MIN_PRIORS:
        raise DegenerateAlignment(
            f"only {len(c2w_sfm)} registered frame(s) have a prior; need {MIN_PRIORS}"
        )
    src, dst = c2w_sfm[:, :3, 3], prior_c2w[:, :3, 3]
    used = np.ones(len(src), bool)
    method = "positions"
    for _ in range(3):  # fit, trim, refit, trim, final fit
        try:
            sim = umeyama(src[used], dst[used], min_spread=MIN_SPREAD)
        except DegenerateAlignment as err:
            if "coincide" in str(err):
                raise
            sim, method = _orientation_fit(c2w_sfm[used], prior_c2w[used]), "orientations+positions"
        res = np.linalg.norm(sim.apply_points(src) - dst, axis=1)
        keep = res <= TRIM_FACTOR * max(float(np.median(res[used])), 1e-9)
        if keep.sum() < MIN_PRIORS or np.array_equal(keep, used):
            break
        used = keep
    return PriorFit(sim=sim, used=used, method=method)


def _orientation_fit(c2w_sfm: np.ndarray, prior_c2w: np.ndarray) -> Similarity:
    """Rotation from orientations (chordal L2 mean of R_prior R_sfm^T), then scale and shift
    from the centres by least squares."""
    m = np.einsum("nij,nkj->ik", prior_c2w[:, :3, :3], c2w_sfm[:, :3, :3])
    u, _, vt = np.linalg.svd(m)
    rot = u @ np.diag([1.0, 1.0, np.linalg.det(u @ vt)]) @ vt
    src, dst = c2w_sfm[:, :3, 3] @ rot.T, prior_c2w[:, :3, 3]
    xs, xd = src - src.mean(0), dst - dst.mean(0)
    denom = float((xs**2).sum())
    if denom <= 1e-18:
        raise DegenerateAlignment("the recovered camera centres all coincide (no baseline)")
    scale = float((xs * xd).sum() / denom)
    return Similarity(rot, dst.mean(0) - scale * src.mean(0), scale)


def fit_swarm_to_priors(
    c2w_sfm: np.ndarray, prior_c2w: np.ndarray, drones: np.ndarray
) -> tuple[PriorFit, bool]:
    """:func:`fit_to_priors` for a swarm (``drones``: int [R], the drone of every frame).

    When the drones' telemetry shares one frame (external positioning, or a common take-off
    frame) one similarity fits all of them and is returned with True. When every drone's
    onboard state has its own origin and heading, one similarity cannot fit them all (its
    residual exceeds :data:`SHARED_FACTOR` x the per-drone fits'); the priors then still give
    the metric scale (median of the per-drone scales) and gravity (the mean of the up direction
    each drone's fit gives in the SfM frame, turned onto +z), returned with False: metres and
    z up, but not the telemetry's position and heading.

    Raises:
        DegenerateAlignment: no drone (and not all together) has enough priors for a fit.
    """
    together = fit_to_priors(c2w_sfm, prior_c2w)
    own = {}
    for d in np.unique(drones):
        m = drones == d
        try:
            own[int(d)] = (fit_to_priors(c2w_sfm[m], prior_c2w[m]), m)
        except DegenerateAlignment:
            continue
    if len(own) < 2:
        return together, True
    rmse_all = together.agreement(c2w_sfm, prior_c2w)["position_rmse_m"]
    rmse_own = float(
        np.median(
            [f.agreement(c2w_sfm[m], prior_c2w[m])["position_rmse_m"] for f, m in own.values()]
        )
    )
    if rmse_all <= max(SHARED_FACTOR * rmse_own, SHARED_MIN_M):
        return together, True
    scale = float(np.median([f.sim.scale for f, _ in own.values()]))
    ups = np.array([f.sim.rotation.T @ np.array([0.0, 0.0, 1.0]) for f, _ in own.values()])
    up = ups.mean(0) / max(float(np.linalg.norm(ups.mean(0))), 1e-12)
    used = np.zeros(len(drones), bool)
    for f, m in own.values():
        used[np.flatnonzero(m)[f.used]] = True
    return PriorFit(Similarity(_turn_onto_z(up), np.zeros(3), scale), used, "scale+gravity"), False


def _turn_onto_z(up: np.ndarray) -> np.ndarray:
    """The smallest rotation [3, 3] taking the unit vector ``up`` onto +z."""
    z = np.array([0.0, 0.0, 1.0])
    axis = np.cross(up, z)
    s, c = float(np.linalg.norm(axis)), float(np.dot(up, z))
    if s < 1e-12:
        return np.eye(3) if c > 0 else np.diag([1.0, -1.0, -1.0])
    k = axis / s
    kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + s * kx + (1 - c) * kx @ kx
