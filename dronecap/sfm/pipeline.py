"""The ``dronecap sfm`` stage: frames.h5 -> posed.h5 plus the COLMAP model, PLY and report.

Outputs (all written atomically):

- ``posed.h5`` (kind "posed"): the registered frames only, c2w poses (OpenCV axes) in the
  normalised scene frame, the COLMAP camera as intrinsics, AABB, per-view near/far, the
  similarity applied (``normalization``), provenance with the hash of frames.h5;
- ``<sfm_dir>/model/``: the chosen COLMAP model (binary, COLMAP's own frame and units);
- ``<sfm_dir>/points.ply``: the sparse points kept by the outlier removal, in the scene frame;
- ``<sfm_dir>/report.json``: see :mod:`dronecap.sfm.report` and docs/sfm.md.

``<sfm_dir>/work/`` keeps COLMAP's database, image folder, raw models and log for inspection.
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from dronecap.camera import Camera
from dronecap.camera.colmap import camera_from_colmap
from dronecap.datasets.colmap_model import model_arrays
from dronecap.datasets.format import Dataset, open_dataset, provenance, write_dataset
from dronecap.datasets.normalize import apply_to_points, apply_to_poses, near_far, normalize_scene
from dronecap.errors import InputError
from dronecap.files import atomic_output, sha256_file
from dronecap.sfm.align import (
    DegenerateAlignment,
    accuracy_against,
    load_ground_truth,
    load_swarm_ground_truth,
)
from dronecap.sfm.camera_plan import CameraPlan, plan_camera
from dronecap.sfm.drones import drone_records
from dronecap.sfm.features import MIN_KEYPOINTS
from dronecap.sfm.flights import flight_of
from dronecap.sfm.options import SfmOptions
from dronecap.sfm.priors import fit_swarm_to_priors, fit_to_priors, read_priors
from dronecap.sfm.reconstruct import ColmapResult
from dronecap.sfm.report import ADVICE, drop_reason, dropped_runs, format_report, pose_jumps
from dronecap.sfm.retries import reconstruct_with_retries

MIN_FRAMES = 3
PER_FRAME_EXTRAS = (
    "prior_c2w",
    "prior_valid",
    "frame_id",
)  # frames.h5 extras with one row per frame


def build_report(res: ColmapResult, ds: Dataset, registered: np.ndarray) -> dict[str, Any]:
    """Report fields that do not need the normalised scene (see :mod:`dronecap.sfm.report`)."""
    n = ds.n
    summary = res.summary
    keypoints = summary.get("keypoints", {})
    partners = summary.get("match", {}).get("verified_partners", {})
    missing = np.setdiff1d(np.arange(n), registered)
    src = ds.source_index if ds.source_index is not None else np.arange(n)
    dropped = [
        {
            "frame": int(i),
            "source_index": int(src[i]),
            "name": ds.names[i] if ds.names else res.names[i],
            "reason": drop_reason(
                keypoints.get(res.names[i], 0), partners.get(res.names[i], 0), MIN_KEYPOINTS
            ),
        }
        for i in missing
    ]
    match_info = {k: v for k, v in summary.get("match", {}).items() if k != "verified_partners"}
    flights = summary.get("flights")
    # a swarm: the rate counts the frames of the drones linked into the model (the others are
    # reported by name with their own model)
    linked = int(np.isin(ds.drones(), flights["main"]).sum()) if flights else n
    return {
        "status": "ok",
        "message": summary.get("stopped") or "",
        "frames_total": n,
        "frames_linked": linked,
        "registered": len(registered),
        "registration_rate": len(registered) / max(linked, 1),
        "flights": flights,
        "dropped": dropped,
        "dropped_runs": dropped_runs(missing, n),
        "models": summary.get("models", {}),
        "chosen_model": summary["best"] and str(Path(summary["best"]).relative_to(res.work)),
        "matching": match_info,
        "init_pair": summary.get("init_pair"),
        "global_mapper": summary.get("global_mapper"),
        "chunks": summary.get("chunks"),
        "keyframes": summary.get("keyframes"),
        "bend_check": summary.get("bend_check"),
        "pose_jumps_remapped": summary.get("pose_jumps_remapped"),
        "keypoints_per_frame_median": float(np.median(list(keypoints.values())))
        if keypoints
        else 0.0,
        "sift_first_octave": summary.get("first_octave"),
        "times": {k: round(v, 3) for k, v in res.times.items()},
        "cpu_seconds": summary.get("cpu", {}),  # per COLMAP phase, all threads
    }


@dataclass
class Placed:
    """The registered frames placed in the scene frame (plus prior-fallback frames)."""

    frames: np.ndarray  # int [M] frame indices into frames.h5, sorted
    poses: np.ndarray  # float64 [M, 4, 4] c2w, OpenCV axes, scene frame
    near_far: np.ndarray  # float64 [M, 2]
    fallback: np.ndarray  # int [F] frames posed from their telemetry prior
    aabb: np.ndarray  # float64 [2, 3]
    scene_from_model: np.ndarray  # float64 [4, 4] similarity, scene from COLMAP's frame
    world_from_scene: np.ndarray | None  # float64 [4, 4] to the priors' world (metres, z up)
    cameras: list[Camera]  # the camera of every drone (one for a single flight)
    kept_points: np.ndarray  # bool [P] the model's points (point-id order) kept for the bounds


def run_sfm(
    frames_path: Path,
    posed_path: Path,
    sfm_dir: Path,
    opts: SfmOptions,
    gt_path: Path | None = None,
    progress: bool = True,
    camera_from: Path | None = None,
) -> dict[str, Any]:
    """Recover poses of ``frames_path`` and write ``posed_path`` and ``sfm_dir`` outputs.

    ``camera_from``: an earlier posed.h5 of the same drone whose camera is used (see
    :mod:`dronecap.sfm.camera_plan`). Returns the report dict (also printed when ``progress``
    and stored as report.json).

    Raises:
        InputError: unreadable input, too few frames, nothing reconstructed, or a registration
            rate below ``opts.min_registration`` (the report is still written; posed.h5 is not).
    """
    t0 = time.perf_counter()
    try:
        opts.validate()
    except ValueError as err:
        raise InputError(str(err)) from None
    if opts.ray:
        from dronecap.sfm.ray_front import check_address

        check_address(opts.ray)
    ds = open_dataset(frames_path)
    gt = _ground_truth(ds, gt_path)
    if ds.n < MIN_FRAMES:
        raise InputError(f"only {ds.n} frame(s); SfM needs at least {MIN_FRAMES}", frames_path)
    plan = plan_camera(ds, opts.camera, camera_from)
    known = None
    if plan.mode == "estimate" and camera_from is None:
        known = plan_camera(ds, "auto")  # the calibrated camera(s) as a remedy, when known
        known = known if known.mode == "fixed" else None
    sfm_dir.mkdir(parents=True, exist_ok=True)
    best, attempts = reconstruct_with_retries(
        ds.images, sfm_dir, opts, plan, known, progress, ds.drones()
    )
    res, rec = best.result, best.result.reconstruction
    registered = np.zeros(0, np.int64) if rec is None else model_arrays(rec, res.names)[0]
    report = build_report(res, ds, registered)
    report["attempts"] = [a.to_dict() for a in attempts]
    report["remedy"] = best.remedies[-1] if best.remedies else None
    if rec is None or rec.num_reg_images() < MIN_FRAMES:
        report["status"] = "failed"
        report["message"] = (
            f"nothing usable came out: {res.summary.get('stopped') or 'no model with 3+ frames'}; "
            + ADVICE
        )
        _finish(report, sfm_dir, t0, progress)
        raise InputError(report["message"], frames_path)
    placed = place_scene(ds, rec, res.names, opts, plan, report, gt)
    t = time.perf_counter()
    with atomic_output(sfm_dir / "model") as tmp:
        tmp.mkdir()
        rec.write_binary(tmp)
    write_points_ply(sfm_dir / "points.ply", rec, placed.scene_from_model, placed.kept_points)
    report["times"]["write_model"] = round(time.perf_counter() - t, 3)
    if report["registration_rate"] < opts.min_registration:
        report["status"] = "failed"
        report["message"] = (
            f"only {100 * report['registration_rate']:.1f}% of frames registered, below "
            f"--min-registration {100 * opts.min_registration:.0f}%; {ADVICE}"
        )
        _finish(report, sfm_dir, t0, progress)
        raise InputError(report["message"], frames_path)
    write_dataset(
        posed_path, posed_dataset(ds, placed, opts, plan, camera_from, frames_path, gt_path)
    )
    _finish(report, sfm_dir, t0, progress)
    return report


def _ground_truth(ds: Dataset, gt_path: Path | None) -> dict[int, np.ndarray] | None:
    """The ground truth of ``ds``'s frames from ``gt_path``: frame index -> c2w [4, 4] (None
    without a path). A swarm's ``swarm.json`` gives every drone's file, found by drone name."""
    if gt_path is None:
        return None
    src = ds.source_index if ds.source_index is not None else np.arange(ds.n)
    times = ds.timestamps if ds.timestamps is not None else np.arange(ds.n, dtype=float)
    drones = ds.drones()
    files = load_swarm_ground_truth(gt_path)
    if not files:
        if drones.max(initial=0) > 0:
            raise InputError("these frames come from several drones: give the swarm.json", gt_path)
        gt = load_ground_truth(gt_path, src, times)
        return {i: gt[int(s)] for i, s in enumerate(src) if int(s) in gt}
    out: dict[int, np.ndarray] = {}
    for d in np.unique(drones):
        name = ds.drone_name(int(d))
        if name not in files:
            raise InputError(f"has no ground truth for drone {name!r}", gt_path)
        mine = np.flatnonzero(drones == d)
        gt = load_ground_truth(files[name], src[mine], times[mine])
        out.update({int(i): gt[int(src[i])] for i in mine if int(src[i]) in gt})
    return out


def place_scene(
    ds: Dataset,
    rec: Any,
    names: list[str],
    opts: SfmOptions,
    plan: CameraPlan,
    report: dict[str, Any],
    gt: Any,
) -> Placed:
    """Align the model to telemetry priors (when present), normalise and bound it, and fill
    the report's priors, camera, quality, scene and accuracy (with ``gt``) records."""
    t = time.perf_counter()
    idx, c2w, points, seen = model_arrays(rec, names)
    drones = ds.drones()
    swarm = len(plan.cameras) > 1
    priors = read_priors(ds)
    metric, up = np.eye(4), None
    if priors is not None:
        report["priors"], metric = _align_to_priors(c2w, idx, priors, drones)
        if "error" not in report["priors"]:
            up = np.array([0.0, 0.0, 1.0])
    c2w_w, points_w = apply_to_poses(metric, c2w), apply_to_points(metric, points)
    norm = normalize_scene(c2w_w, points_w, up=up)
    poses = apply_to_poses(norm.matrix, c2w_w)
    pts = apply_to_points(norm.matrix, points_w)
    nf = near_far(poses, norm.aabb, [pts[s] for s in seen])
    cameras = model_cameras(rec, names, plan)
    report["times"]["normalize"] = round(time.perf_counter() - t, 3)
    report["camera"] = _camera_report(cameras[0], plan)
    report["quality"] = {
        "mean_reprojection_error_px": float(rec.compute_mean_reprojection_error()),
        "mean_track_length": float(rec.compute_mean_track_length()),
        "points": int(len(points)),
        "points_kept": int(norm.inliers.sum()),
        "pose_jumps": pose_jumps(c2w[:, :3, 3], idx, drones[idx]),
    }
    report["scene"] = {
        "normalization": (norm.matrix @ metric).tolist(),
        "aabb": norm.aabb.tolist(),
        "near_far_median": np.median(nf, 0).tolist(),
    }
    fallback = np.zeros(0, np.int64)
    shared = priors is not None and report["priors"].get("shared_frame", True)
    if opts.prior_fallback and shared and "error" not in report["priors"]:
        fallback = np.setdiff1d(np.flatnonzero(priors[1]), idx)
        poses = np.concatenate([poses, apply_to_poses(norm.matrix, priors[0][fallback])])
        nf = np.concatenate([nf, near_far(poses[len(idx) :], norm.aabb, [])])
        report["priors"]["fallback_frames"] = fallback.tolist()
    if gt is not None:  # in the frame before normalisation (metres with priors: scale 1)
        groups = ds.drones()[idx] if swarm else None
        report["accuracy"] = accuracy_against(c2w_w, idx, gt, np.arange(ds.n), groups)
    if swarm:
        report["drones"] = drone_records(ds, idx, cameras, plan, report)
    order = np.argsort(np.concatenate([idx, fallback]), kind="stable")
    frames = np.concatenate([idx, fallback])[order]
    return Placed(
        frames,
        poses[order],
        nf[order],
        fallback,
        norm.aabb,
        norm.matrix @ metric,
        None if up is None else np.linalg.inv(norm.matrix),
        cameras,
        norm.inliers,
    )


def model_cameras(rec: Any, names: list[str], plan: CameraPlan) -> list[Camera]:
    """The camera of every drone (one for a single flight): the known one exactly as given
    when fixed (no text round trip), else the model's camera of the drone's frames (the start
    camera for a drone with no registered frame)."""
    if plan.mode == "fixed":
        return [k for k in plan.cameras if k is not None]
    by_drone: dict[int, Camera] = {}
    for image_id in rec.reg_image_ids():
        d = flight_of(rec.images[image_id].name)
        if d not in by_drone:
            cam = rec.cameras[rec.images[image_id].camera_id]
            by_drone[d] = camera_from_colmap(
                cam.model_name, np.asarray(cam.params), cam.width, cam.height
            )
    start = next(iter(by_drone.values()))
    return [by_drone.get(d, k or start) for d, k in enumerate(plan.cameras)]


def posed_dataset(
    ds: Dataset,
    placed: Placed,
    opts: SfmOptions,
    plan: CameraPlan,
    camera_from: Path | None,
    frames_path: Path,
    gt_path: Path | None,
) -> Dataset:
    """The posed.h5 dataset: ``placed``'s frames of ``ds`` with their poses, bounds, camera,
    per-frame extras and provenance."""
    posed = ds.subset(placed.frames)
    posed.kind = "posed"
    posed.poses = placed.poses
    if len(placed.cameras) > 1:  # a camera per drone, the drone's index into the table
        posed.set_cameras(placed.cameras, ds.drones()[placed.frames])
    else:
        posed.cameras = posed.camera_index = None
        posed.intrinsics = placed.cameras[0]
    posed.aabb = placed.aabb
    posed.near_far = placed.near_far
    posed.normalization = placed.scene_from_model
    for name in PER_FRAME_EXTRAS:
        if name in ds.extra and len(ds.extra[name]) == ds.n:
            posed.extra[name] = np.asarray(ds.extra[name])[placed.frames]
    posed.extra["pose_source"] = np.isin(placed.frames, placed.fallback).astype(np.int8)
    hashes = {"frames.h5": sha256_file(frames_path)}
    if gt_path is not None:
        hashes["gt"] = sha256_file(gt_path)
    given = {**opts.to_dict(), "camera_from": str(camera_from) if camera_from else None}
    posed.provenance = provenance("sfm", given, hashes)
    n_reg = len(placed.frames) - len(placed.fallback)
    posed.attrs = {
        **ds.attrs,
        "sfm_registered": n_reg,
        "sfm_frames_total": ds.n,
        "sfm_camera": {"mode": plan.mode, "source": plan.source},
        "pixel_centres": "intrinsics in COLMAP's convention: pixel (u, v) centred at (u+.5, v+.5)",
    }
    if placed.world_from_scene is not None:
        m = placed.world_from_scene
        posed.attrs["world_from_scene"] = m.tolist()
        posed.attrs["metres_per_scene_unit"] = float(np.cbrt(np.linalg.det(m[:3, :3])))
    return posed


def _align_to_priors(
    c2w: np.ndarray, idx: np.ndarray, priors: tuple[np.ndarray, np.ndarray], drones: np.ndarray
) -> tuple[dict[str, Any], np.ndarray]:
    """Fit the registered poses [R, 4, 4] (frames ``idx``) to their telemetry priors; a swarm
    (``drones``: int [N], the drone of every frame) through :func:`fit_swarm_to_priors`.

    Returns the report's "priors" record and the 4x4 similarity (identity when the fit fails).
    """
    prior_c2w, valid = priors
    have = valid[idx]
    info: dict[str, Any] = {
        "frames_with_prior": int(valid.sum()),
        "registered_with_prior": int(have.sum()),
    }
    own, theirs = c2w[have], prior_c2w[idx[have]]
    try:
        if drones.max(initial=0) > 0:
            fit, info["shared_frame"] = fit_swarm_to_priors(own, theirs, drones[idx[have]])
        else:
            fit = fit_to_priors(own, theirs)
    except DegenerateAlignment as err:
        info["error"] = f"not aligned to the priors: {err}"
        return info, np.eye(4)
    info.update(method=fit.method, used=int(fit.used.sum()), scale_m_per_unit=fit.sim.scale)
    if info.get("shared_frame", True):  # positions compare only in one shared frame
        info.update(fit.agreement(own, theirs))
    return info, fit.sim.matrix()


def _camera_report(k: Camera, plan: CameraPlan) -> dict[str, Any]:
    """The report's camera record: the camera used, how it was handled, where it came from."""
    out: dict[str, Any] = {
        "model": k.model,
        "fx": k.fx,
        "fy": k.fy,
        "cx": k.cx,
        "cy": k.cy,
        "distortion": list(k.distortion),
        "mode": plan.mode,
        "source": plan.source,
        "fixed": plan.mode == "fixed",
    }
    if plan.camera is not None and plan.mode != "fixed":
        out["start_fx"] = plan.camera.fx
    return out


def write_points_ply(path: Path, rec: Any, scene_from_model: np.ndarray, kept: np.ndarray) -> None:
    """The sparse points of ``rec`` kept by the outlier removal (``kept``, bool [P] in point-id
    order), in the scene frame (``scene_from_model``, 4x4 similarity), with their colours:
    pycolmap's PLY export of a transformed copy."""
    import pycolmap

    copy = pycolmap.Reconstruction(rec)
    for pid, keep in zip(sorted(copy.points3D.keys()), kept, strict=True):
        if not keep:
            copy.delete_point3D(pid)
    scale = float(np.cbrt(np.linalg.det(scene_from_model[:3, :3])))
    rot = pycolmap.Rotation3d(scene_from_model[:3, :3] / scale)
    copy.transform(pycolmap.Sim3d(scale, rot, scene_from_model[:3, 3]))
    with atomic_output(path) as tmp:
        copy.export_PLY(tmp)


def _finish(report: dict[str, Any], sfm_dir: Path, t0: float, progress: bool) -> None:
    report["times"]["total"] = round(time.perf_counter() - t0, 3)
    with atomic_output(sfm_dir / "report.json") as tmp:
        tmp.write_text(json.dumps(report, indent=1))
    if progress:
        print(format_report(report))
