"""``dronecap sfm``: recover camera poses with COLMAP, normalise and bound -> posed.h5."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from dronecap.settings import Settings as Base
from dronecap.settings import flatten, output_setting, setting
from dronecap.sfm.options import SfmOptions

# The SfmOptions fields offered as options, with their help (the others keep their defaults).
OPTION_HELP = {
    "max_features": "SIFT keypoints kept per frame",
    "first_octave": "-1 upsamples tiny frames before SIFT, 0 does not",
    "finer_below": "frames with fewer SIFT keypoints than this (median) are extracted again "
    "one octave finer (0: never)",
    "matcher": "auto | sequential | exhaustive",
    "exhaustive_below": "auto: exhaustive below this many frames",
    "overlap": "sequential: frames matched after each frame",
    "loop_period": "loop detection: query every this-many-th frame",
    "loop_num_images": "loop detection: frames retrieved per query",
    "cross_num_images": "a swarm: frames of the other drones' flights matched with each frame",
    "ray": "features and sequential pairs of each piece of a flight as a Ray task: 'local' or "
    "a Ray cluster address ('auto', ray://HOST:10001); empty: here",
    "ray_piece_frames": "--ray: frames of one task (each flight is cut into pieces this long)",
    "min_registration": "fail below this registered fraction",
    "seed": "mapper random seed",
    "init_trials": "2: also map from COLMAP's initial pair; keep best",
    "num_threads": "COLMAP threads (-1: all cores)",
    "camera": "fixed | refine | estimate; auto: fixed when frames.h5 has a calibrated camera",
    "init_max_gap": "initial pair: at most this many frames apart",
    "retry_below": "retry with remedies below this registered fraction",
    "retry_budget": "seconds after which no new retry starts",
    "clahe": "contrast-normalise frames before SIFT (low-contrast, vignetted footage)",
    "prior_fallback": "frames that fail to register keep their telemetry prior pose in posed.h5",
    "time_cap": "seconds of mapping after which the model so far is kept (0: no cap)",
    "ba_global_ratio": "global bundle adjustment when the model grew by this factor",
    "loop_pairs": "loop pairs from: words (our bag of words) | index (pycolmap's visual index) "
    "| none",
    "mapper": "incremental | global (GLOMAP, kept only when complete and not bent)",
    "chunk_above": "a single flight of more usable frames than this is mapped in overlapping "
    "chunks, merged and bundle-adjusted once (0: never)",
    "keyframe_flow": "a long single flight maps only frames whose matches moved up to this many "
    "px from the last one mapped, then registers the others without bundle adjustment (0: map "
    "every frame)",
    "keyframes_above": "flights of fewer usable frames than this map every frame",
    "quadratic_overlap": "sequential: pair frame i with i+2^k (COLMAP default) instead of "
    "i+1..i+overlap",
}


@dataclass(kw_only=True)
class Settings(Base):
    """Options of ``dronecap sfm`` (COLMAP's are SfmOptions fields, defaults from there)."""

    frames: str | None = setting(None, help="input frames.h5 (default: WORKDIR/frames.h5)")
    output: str | None = output_setting("output posed.h5", "WORKDIR/posed.h5")
    sfm_dir: str | None = setting(None, help="model, PLY and report folder (default: WORKDIR/sfm)")
    gt: str | None = setting(
        None,
        help="ground truth to measure accuracy against: the simulator's flight.json/poses.json, "
        "or a TUM trajectory (matched to the frames by timestamp, within 20 ms)",
    )
    camera_from: str | None = setting(
        None, help="posed.h5 of an earlier reconstruction of the same drone: use its camera"
    )
    options: dict[str, Any] = flatten(
        SfmOptions,
        only=tuple(OPTION_HELP),
        flags={"loop_num_images": "loop-images", "num_threads": "threads"},
        help=lambda f: (
            OPTION_HELP[f.name] + ("" if f.type == "bool" else f" (default: {f.default})")
        ),
    )
    no_loop_detection: bool = setting(
        False, help="sequential: no loop pairs from the flight's visual index"
    )
    no_extend: bool = setting(
        False, help="do not resume mapping from the largest model to absorb the others"
    )
    quiet: bool = setting(False, help="no progress bar and no printed report")


def run(s: Settings) -> int:
    """Run the stage; 0 on success (InputError -> exit 1 via the CLI)."""
    from pathlib import Path

    from dronecap import workspace
    from dronecap.sfm.pipeline import run_sfm

    given = dict(s.options)
    if s.no_loop_detection:
        given["loop_detection"] = False
    if s.no_extend:
        given["extend"] = False
    report = run_sfm(
        frames_path=workspace.resolve(s.workdir, s.frames, workspace.FRAMES),
        posed_path=workspace.resolve(s.workdir, s.output, workspace.POSED),
        sfm_dir=workspace.resolve(s.workdir, s.sfm_dir, workspace.SFM_DIR),
        opts=SfmOptions(**given),
        gt_path=Path(s.gt) if s.gt else None,
        progress=not s.quiet,
        camera_from=Path(s.camera_from) if s.camera_from else None,
    )
    return 0 if report["status"] == "ok" else 1
