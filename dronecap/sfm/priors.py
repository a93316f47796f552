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
