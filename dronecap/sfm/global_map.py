"""Global mapping (pycolmap's GLOMAP: rotation averaging, global positioning, bundle adjustment),
guarded: it is kept only when it registers as many frames as asked and the bend check
(:mod:`dronecap.sfm.bend`) finds it straight, for consecutive frames and for frames
``overlap`` apart; otherwise the caller maps incrementally.

Why the guard: at 160 px GLOMAP has reported every frame registered with 10-32 % trajectory
error (issue 15; the simulated corridor 9.5 %). Its registration count alone is never trusted.
Most of that error came from pairs labelled planar, whose pose GLOMAP takes from a homography
decomposition: with the global mapper, verification calls a pair planar only when a homography
explains more matches than the essential matrix (``SfmOptions.global_max_h_inlier_ratio``).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from dronecap.sfm.bend import WIDE_P95_DEG, rotation_disagreement
from dronecap.sfm.colmap_steps import write_model
from dronecap.sfm.options import SfmOptions


def global_options(opts: SfmOptions, refine_camera: bool) -> Any:
    """GlobalPipelineOptions for small gray frames (no GPU, our seed and thread count)."""
    import pycolmap

    g = pycolmap.GlobalPipelineOptions()
    g.min_num_matches = opts.min_num_matches
    g.num_threads = opts.num_threads
    g.random_seed = opts.seed
    g.multiple_models = False
    m = g.mapper
    m.num_threads = opts.num_threads
    m.random_seed = opts.seed
    m.global_positioning.use_gpu = False
    m.bundle_adjustment.ceres.use_gpu = False
    m.bundle_adjustment.refine_focal_length = refine_camera
    m.bundle_adjustment.refine_extra_params = refine_camera
    m.bundle_adjustment.refine_principal_point = False
    return g


def global_map(
    database: Path, image_dir: Path, out_dir: Path, opts: SfmOptions, refine_camera: bool
) -> tuple[dict[str, dict[str, float]], dict[str, Any]]:
    """Map with GLOMAP into ``out_dir/<k>``; returns the models (folder -> frames, reprojection)
    and the guard's record: frames of the largest model, its bend check (consecutive frames,
    and frames ``opts.overlap`` apart: ``wide_check``) and ``kept``."""
    import pycolmap

    out_dir.mkdir(parents=True, exist_ok=True)
    models = pycolmap.global_mapping(
        database, image_dir, out_dir, global_options(opts, refine_camera)
    )
    found = {}
    for k, rec in models.items():
        found.update(write_model(rec, out_dir / str(k)))
    record: dict[str, Any] = {"frames": 0, "kept": False}
    if found:
        best = max(found, key=lambda j: found[j]["frames"])
        record.update(
            frames=found[best]["frames"],
            bend_check=rotation_disagreement(database, Path(best), threads=opts.num_threads),
            wide_check=rotation_disagreement(
                database, Path(best), max(opts.overlap, 1), opts.num_threads
            ),
        )
    return found, record


def accept(record: dict[str, Any], usable: int, min_fraction: float) -> bool:
    """Whether a global model (its ``record`` from :func:`global_map`) may be kept: at least
    ``min_fraction`` of the ``usable`` frames, not bent, and its bend check's tail as narrow as
    a straight model's (:data:`dronecap.sfm.bend.TAIL_P95_DEG`), and frames further apart
    agreeing as closely (:data:`dronecap.sfm.bend.WIDE_P95_DEG`)."""
    bend = record.get("bend_check") or {}
    wide = record.get("wide_check") or {}
    return (
        record["frames"] >= min_fraction * usable
        and bend.get("pairs", 0) > 0
        and not bend["bent"]
        and bend["tail_ok"]
        and wide.get("pairs", 0) > 0
        and wide["p95_deg"] <= WIDE_P95_DEG
    )
