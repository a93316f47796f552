"""Pose accuracy against ground truth: Umeyama similarity alignment, ATE and rotation errors.

SfM recovers a trajectory only up to a similarity (rotation, translation, scale). Before
comparing it with ground truth we fit that similarity to the camera centres (Umeyama 1991,
least squares) and measure what is left. The fit needs camera centres that span at least a
plane: with collinear centres the rotation about the line is undetermined, with (nearly)
identical centres even the scale is; both cases raise :class:`DegenerateAlignment` rather than
returning an arbitrary answer.
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from dronecap.errors import InputError

WEAK_ALIGNMENT = 3.0  # warn when ATE RMSE > (RMS sideways spread of the centres) / this


class DegenerateAlignment(InputError):
    """The camera centres do not determine a similarity (too few, coincident or collinear)."""


@dataclass
class Similarity:
    """x_target = scale * rotation @ x_source + translation."""

    rotation: np.ndarray  # float64 [3, 3], det +1
    translation: np.ndarray  # float64 [3]
    scale: float

    def matrix(self) -> np.ndarray:
        """The 4x4 homogeneous matrix of the similarity, float64."""
        m = np.eye(4)
        m[:3, :3] = self.scale * self.rotation
        m[:3, 3] = self.translation
        return m

    def apply_points(self, x: np.ndarray) -> np.ndarray:
        """Map points [N, 3] -> [N, 3]."""
        return self.scale * x @ self.rotation.T + self.translation

    def apply_poses(self, c2w: np.ndarray) -> np.ndarray:
        """Map camera-to-world poses [N, 4, 4] (rotation part stays orthonormal)."""
        out = np.array(c2w, dtype=np.float64, copy=True)
        out[:, :3, :3] = self.rotation @ out[:, :3, :3]
        out[:, :3, 3] = self.apply_points(out[:, :3, 3])
        return out


def umeyama(source: np.ndarray, target: np.ndarray, min_spread: float = 1e-3) -> Similarity:
    """Least-squares similarity mapping ``source`` points onto ``target`` points.

    Args:
        source: [N, 3] points (e.g. SfM camera centres, arbitrary units).
        target: [N, 3] corresponding points (e.g. ground-truth centres, metres).
        min_spread: the second singular value of each centred point set must be at least this
            fraction of the first; below it the points are (nearly) collinear and the rotation
            about their line is not determined.

    Raises:
        DegenerateAlignment: fewer than 3 points, coincident points, or collinear points.
    """
    src = np.asarray(source, dtype=np.float64)
    dst = np.asarray(target, dtype=np.float64)
    if src.shape != dst.shape or src.ndim != 2 or src.shape[1] != 3:
        raise ValueError(f"need two [N, 3] arrays, got {src.shape} and {dst.shape}")
    n = src.shape[0]
    if n < 3:
        raise DegenerateAlignment(f"only {n} camera centres: a similarity needs at least 3")
    mu_s, mu_d = src.mean(0), dst.mean(0)
    xs, xd = src - mu_s, dst - mu_d
    for name, x, ref in (("recovered", xs, src), ("ground-truth", xd, dst)):
        sv = np.linalg.svd(x, compute_uv=False)
        size = max(float(np.abs(ref).max()), 1.0)
        if sv[0] <= 1e-9 * size * np.sqrt(n):
            raise DegenerateAlignment(f"the {name} camera centres all coincide (no baseline)")
        if sv[1] < min_spread * sv[0]:
            raise DegenerateAlignment(
                f"the {name} camera centres are collinear (spread ratio {sv[1] / sv[0]:.1e}):"
                " the rotation about the flight line is undetermined"
            )
    cov = xd.T @ xs / n
    u, d, vt = np.linalg.svd(cov)
    s = np.eye(3)
    if np.linalg.det(u) * np.linalg.det(vt) < 0:
        s[2, 2] = -1.0
    rot = u @ s @ vt
    var_s = (xs**2).sum() / n
    scale = float(np.trace(np.diag(d) @ s) / var_s)
    trans = mu_d - scale * rot @ mu_s
    return Similarity(rot, trans, scale)


@dataclass
class PoseAccuracy:
    """Trajectory error after similarity alignment (all distances in ground-truth units)."""

    matched: int  # recovered frames that have ground truth
    total_gt: int  # ground-truth frames among the input frames
    registration_rate: float  # matched / total_gt
    ate_rmse: float  # RMSE of camera-centre error after alignment
    ate_max: float
    extent: float  # diagonal of the ground-truth centres' bounding box (of the matched frames)
    ate_percent: float  # 100 * ate_rmse / extent
    rot_median_deg: float  # median camera rotation error after alignment, degrees
    rot_max_deg: float
    step_rot_median_deg: float  # rotation error between consecutive frames: needs no alignment
    step_rot_max_deg: float
    scale: float  # similarity scale recovered -> ground truth
    gravity_deg: float  # angle the alignment turns +z by (meaningful when both frames are z-up)
    warning: str = ""  # set when the position errors rival the trajectory's sideways spread

    def to_dict(self) -> dict[str, float | int | str]:
        """JSON-able record."""
        return {k: (round(v, 6) if isinstance(v, float) else v) for k, v in asdict(self).items()}


def rotation_angle_deg(r: np.ndarray) -> np.ndarray:
    """Angle of rotation matrices [N, 3, 3] in degrees, [N]."""
    cos = (np.trace(r, axis1=1, axis2=2) - 1.0) / 2.0
    return np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))


def step_rotation_errors_deg(est_c2w: np.ndarray, gt_c2w: np.ndarray) -> np.ndarray:
    """Rotation error of each step between consecutive frames, degrees [N - 1].

    The angle between the recovered and the true relative rotation of frames k and k + 1
    (camera k's view of camera k + 1): no similarity is involved, so a model whose shape is right
    scores low here however its global alignment turns out, and a bent model scores high.
    """
    est = np.asarray(est_c2w, dtype=np.float64)[:, :3, :3]
    gt = np.asarray(gt_c2w, dtype=np.float64)[:, :3, :3]
    rel_est = np.einsum("nji,njk->nik", est[:-1], est[1:])  # R_k^T R_k+1
    rel_gt = np.einsum("nji,njk->nik", gt[:-1], gt[1:])
    return rotation_angle_deg(np.einsum("nji,njk->nik", rel_gt, rel_est))


def pose_accuracy(
    est_c2w: np.ndarray, gt_c2w: np.ndarray, total_gt: int | None = None
) -> PoseAccuracy:
    """Align ``est_c2w`` to ``gt_c2w`` with Umeyama on camera centres and measure the errors.

    Args:
        est_c2w: [N, 4, 4] recovered camera-to-world poses (OpenCV axes, any scale).
        gt_c2w: [N, 4, 4] ground-truth poses of the same frames (OpenCV axes).
        total_gt: how many frames should have been recovered (for the registration rate);
            defaults to N.

    Raises:
        DegenerateAlignment: when the centres do not determine a similarity.
    """
    est = np.asarray(est_c2w, dtype=np.float64)
    gt = np.asarray(gt_c2w, dtype=np.float64)
    sim = umeyama(est[:, :3, 3], gt[:, :3, 3])
    aligned = sim.apply_poses(est)
    err = np.linalg.norm(aligned[:, :3, 3] - gt[:, :3, 3], axis=1)
    extent = float(np.linalg.norm(gt[:, :3, 3].max(0) - gt[:, :3, 3].min(0)))
    rel = np.einsum("nji,njk->nik", gt[:, :3, :3], aligned[:, :3, :3])  # R_gt^T R_est
    rot = rotation_angle_deg(rel)
    rmse = float(np.sqrt((err**2).mean()))
    total = len(est) if total_gt is None else total_gt
    centred = gt[:, :3, 3] - gt[:, :3, 3].mean(0)
    side = float(np.linalg.svd(centred, compute_uv=False)[1] / np.sqrt(len(gt)))
    step = step_rotation_errors_deg(est, gt)
    warning = ""
    if rmse > side / WEAK_ALIGNMENT:
        warning = (
            f"ATE {rmse:.3g} is over 1/{WEAK_ALIGNMENT:g} of the trajectory's sideways spread "
            f"{side:.3g}: the alignment rotation (and so the rotation errors) is weakly determined;"
            f" the consecutive-frame rotation errors, which need no alignment, reach "
            f"{step.max():.3g} deg (large: the model itself is bent)"
        )
    return PoseAccuracy(
        matched=len(est),
        total_gt=total,
        registration_rate=len(est) / max(total, 1),
        ate_rmse=rmse,
        ate_max=float(err.max()),
        extent=extent,
        ate_percent=100.0 * rmse / extent if extent > 0 else float("inf"),
        rot_median_deg=float(np.median(rot)),
        rot_max_deg=float(rot.max()),
        step_rot_median_deg=float(np.median(step)),
        step_rot_max_deg=float(step.max()),
        scale=sim.scale,
        gravity_deg=float(np.degrees(np.arccos(np.clip(sim.rotation[2, 2], -1.0, 1.0)))),
        warning=warning,
    )


TUM_MAX_DT = 0.02  # s: a frame matches a TUM pose at most this far away in time


def load_ground_truth(
    path: str | Path,
    source_index: np.ndarray | None = None,
    timestamps: np.ndarray | None = None,
) -> dict[int, np.ndarray]:
    """Ground truth as source frame index -> c2w [4, 4] (OpenCV axes).

    Either the simulator's ``poses.json`` / ``flight.json`` (``{"frames": [{"index": int, "c2w":
    4x4 nested list}, ...]}``) or a TUM trajectory (any file that is not JSON: ``timestamp tx ty
    tz qx qy qz qw`` lines, :func:`dronecap.datasets.trajectory.read_tum`), whose poses are
    matched to the frames (``source_index`` int [N], ``timestamps`` float [N] seconds, same clock)
    by nearest timestamp within :data:`TUM_MAX_DT`.
    """
    path = Path(path)
    if path.suffix.lower() != ".json":
        return _tum_ground_truth(path, source_index, timestamps)
    try:
        data = json.loads(path.read_text())
        out = {int(f["index"]): np.asarray(f["c2w"], dtype=np.float64) for f in data["frames"]}
    except FileNotFoundError:
        raise InputError("ground-truth file not found", path) from None
    except (json.JSONDecodeError, KeyError, TypeError, ValueError) as err:
        msg = f"not a poses.json with frames[].index and frames[].c2w ({err})"
        raise InputError(msg, path) from None
    if any(m.shape != (4, 4) or not np.isfinite(m).all() for m in out.values()):
        raise InputError("every frames[].c2w must be a finite 4x4 matrix", path)
    return out


def load_swarm_ground_truth(path: str | Path) -> dict[str, Path]:
    """A swarm's ground-truth files by drone name, from the simulator's ``swarm.json``
    (``{"drones": [{"name", "ground_truth"}, ...]}``, paths relative to its folder); an empty
    dict when ``path`` is not such a file (a single flight's ground truth)."""
    path = Path(path)
    if path.suffix.lower() != ".json":
        return {}
    try:
        data = json.loads(path.read_text())
    except FileNotFoundError:
        raise InputError("ground-truth file not found", path) from None
    except (json.JSONDecodeError, UnicodeDecodeError) as err:
        raise InputError(f"not JSON ({err})", path) from None
    if not isinstance(data, dict) or "drones" not in data:
        return {}
    try:
        return {str(d["name"]): path.parent / str(d["ground_truth"]) for d in data["drones"]}
    except (KeyError, TypeError) as err:
        raise InputError(f"drones[] need a name and a ground_truth ({err})", path) from None


def _tum_ground_truth(
    path: Path, source_index: np.ndarray | None, timestamps: np.ndarray | None
) -> dict[int, np.ndarray]:
    """TUM poses matched to frames by nearest timestamp (see :func:`load_ground_truth`)."""
    from dronecap.datasets.trajectory import read_tum

    if source_index is None or timestamps is None:
        raise InputError("a TUM ground truth needs the frames' timestamps", path)
    times, c2w = read_tum(path)
    order = np.argsort(times)
    times, c2w = times[order], c2w[order]
    out = {}
    for s, t in zip(np.asarray(source_index), np.asarray(timestamps, float), strict=True):
        j = int(np.clip(np.searchsorted(times, t), 1, len(times) - 1)) if len(times) > 1 else 0
        j = j - 1 if j > 0 and abs(times[j - 1] - t) <= abs(times[j] - t) else j
        if abs(times[j] - t) <= TUM_MAX_DT:
            out[int(s)] = c2w[j]
    if not out:
        raise InputError(
            f"no frame time lies within {TUM_MAX_DT * 1000:.0f} ms of a pose in this TUM file "
            f"(its times {times[0]:.3f}-{times[-1]:.3f} s, the frames' "
            f"{np.min(timestamps):.3f}-{np.max(timestamps):.3f} s)",
            path,
        )
    return out


def accuracy_against(
    c2w: np.ndarray,
    source_index: np.ndarray,
    gt: dict[int, np.ndarray],
    all_source_index: np.ndarray,
    groups: np.ndarray | None = None,
) -> dict[str, Any]:
    """Accuracy record of recovered poses against ground truth, matched by source frame index.

    Args:
        c2w: [R, 4, 4] recovered poses of the registered frames.
        source_index: int [R] source frame number of each registered frame.
        gt: source frame number -> ground-truth c2w [4, 4].
        all_source_index: int [N] source frame numbers of every input frame (the denominator of
            the registration rate counts those with ground truth).
        groups: int [R] a group (drone) per registered frame: adds "per_group" errors.

    Returns:
        :meth:`PoseAccuracy.to_dict`, or {"error": why} when alignment is degenerate or no
        frame has ground truth.
    """
    have = [i for i, s in enumerate(source_index) if int(s) in gt]
    total = sum(int(s) in gt for s in all_source_index)
    if total == 0:
        return {"error": "no input frame's source_index appears in the ground truth"}
    est = np.asarray(c2w)[have]
    ref = np.stack([gt[int(source_index[i])] for i in have]) if have else np.zeros((0, 4, 4))
    try:
        record = pose_accuracy(est, ref, total_gt=total).to_dict()
    except DegenerateAlignment as err:
        return {"error": f"alignment impossible: {err}", "matched": len(have), "total_gt": total}
    if groups is not None:
        record["per_group"] = _group_errors(est, ref, np.asarray(groups)[have])
    return record


def _group_errors(est: np.ndarray, ref: np.ndarray, groups: np.ndarray) -> dict[str, Any]:
    """Per group (a swarm's drone): frames, ATE (percent of the whole trajectory's extent) and
    rotation error median, in the one alignment of every frame (the swarm's common frame)."""
    sim = umeyama(est[:, :3, 3], ref[:, :3, 3])
    aligned = sim.apply_poses(est)
    err = np.linalg.norm(aligned[:, :3, 3] - ref[:, :3, 3], axis=1)
    rot = rotation_angle_deg(np.einsum("nji,njk->nik", ref[:, :3, :3], aligned[:, :3, :3]))
    extent = float(np.linalg.norm(ref[:, :3, 3].max(0) - ref[:, :3, 3].min(0)))
    out = {}
    for g in np.unique(groups):
        m = groups == g
        out[str(int(g))] = {
            "matched": int(m.sum()),
            "ate_percent": round(100.0 * float(np.sqrt((err[m] ** 2).mean())) / extent, 4),
            "rot_median_deg": round(float(np.median(rot[m])), 4),
        }
    return out
