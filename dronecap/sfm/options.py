"""Settings of ``dronecap sfm``: one dataclass, one documented field each, tuned for 160x160.

The defaults come from ``benchmarks/sfm_accuracy.py`` (see docs/sfm.md for the numbers).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, replace
from typing import Any

MATCHERS = ("auto", "sequential", "exhaustive")
LOOP_PAIRS = ("words", "index", "none")
MAPPERS = ("incremental", "global")
CAMERA_MODES = ("auto", "fixed", "refine", "estimate")


# SIFT's finest first octave: -2 upsamples 160-px frames 4x, so the detector reaches blobs a
# quarter pixel across. Finer gives no new structure and costs 4x again.
FINEST_OCTAVE = -2


@dataclass
class SfmOptions:
    """What COLMAP is asked to do, from features to mapping."""

    # --- camera (see sfm/camera_plan.py) ---
    camera: str = "auto"  # fixed | refine | estimate; auto: fixed when the camera is known
    # --- features (SIFT on CPU) ---
    max_features: int = 2048  # SIFT keypoints kept per image (160x160 frames yield ~100-400)
    first_octave: int = -1  # -1 upsamples 2x before the first octave: more features on tiny images
    # Frames with fewer keypoints than this (median) are extracted again one octave finer (4x
    # upsampling at -2) at finer_peak_threshold: real 160-px footage and white-background
    # orbits yield 150-250 at -1 even at 0.004, and at -2 register without retries (Himax
    # test_2, test_15) and pose more accurately (lego orbit ATE 0.42 -> 0.26 %); textured
    # flights keep -1, which is 2x faster there (benchmarks/results/sift_octave.md). 300 with
    # the first pass's 0.01 (it keeps ~440, not 565, keypoints on the 446-frame corridor; at
    # 0.004 the threshold was 400). 0: never.
    finer_below: int = 300
    # SIFT contrast threshold of the first pass (COLMAP default 0.0067). 0.01 since session 19:
    # with verify_min_trials 10 the 446-frame corridor's matching takes 41 instead of 72 CPU-s
    # and its sfm 57 instead of 79 s wall on the idle machine, ATE 0.203 vs 0.212 %, rotation
    # 0.32 vs 0.34 deg (benchmarks/results/sfm_scaling_front2_s19.md). Session 14 kept 0.004
    # because the 3901-frame flight then had no initial pair; the planar fallback has found
    # one there since (docs/sfm.md "Session 14", "Session 19").
    peak_threshold: float = 0.01
    # contrast threshold of the finer re-extraction of sparse frames (0.004 is what sparse
    # footage, Himax and lego, was measured with); matters when peak_threshold is raised
    finer_peak_threshold: float = 0.004
    clahe: bool = False  # contrast-normalise frames (capture.contrast) before SIFT
    # --- matching ---
    matcher: str = "auto"  # "sequential" (video order), "exhaustive", or "auto"
    exhaustive_below: int = 80  # "auto" matches every pair when there are fewer frames than this
    overlap: int = 10  # sequential: each frame is matched with this many following frames
    quadratic_overlap: bool = False  # sequential: pair i with i+2^k instead of i+1..i+overlap
    loop_detection: bool = True  # sequential: add pairs of frames that look alike (loops)
    # how loop pairs are found: "words" our bag of words (sfm/retrieval.py: every loop_period-th
    # frame with its loop_num_images most alike frames over overlap+1 frames away); "index"
    # pycolmap's visual index of the flight; "none". Words: 446-frame corridor 32 CPU-s with
    # the matching of its pairs (the index alone took 55 s), ATE 0.15 % / rotation 0.36 deg;
    # 124 frames ATE 0.12 % vs 0.15 %, 0.34 vs 0.48 deg (benchmarks/results/sfm_scaling.md)
    loop_pairs: str = "words"
    # query the visual index with every this-many-th frame. 10 since session 19 (was 5): half
    # the loop pairs; one run each, 5 -> 10: 446-frame corridor 57 -> 50 s, ATE 0.203 -> 0.191 %;
    # 124 / 223 kept: ATE 0.128 / 0.158 -> 0.144 / 0.159 %, rotation 0.37 / 0.27 -> 0.36 /
    # 0.31 deg; lego orbit video (197 frames, two passes): 0.264 -> 0.237 %, 0.43 -> 0.40 deg
    loop_period: int = 10
    loop_num_images: int = 15  # frames retrieved per query
    visual_words: int = 512  # size of the flight's own visual vocabulary (upper bound)
    cross_num_images: int = 5  # a swarm: frames of other drones' flights matched per frame
    # features and sequential pairs of each piece of chunk_frames frames of a flight (one, or a
    # swarm's) as a Ray task ("local", or a cluster address); "" runs them here (sfm/ray_front.py)
    ray: str = ""
    # frames of one Ray task: the pieces each flight is cut into (a cluster gets more tasks from
    # shorter pieces; every cut adds `overlap` frames' seam pairs matched centrally)
    ray_piece_frames: int = 150
    max_epipolar_error: float = 4.0  # RANSAC threshold of two-view verification, pixels
    # RANSAC trials at least run per pair in two-view verification (COLMAP's default 100).
    # Matches between 160-px video frames are ~99 % inliers, so RANSAC's own stopping rule asks
    # for a handful of trials; the floor was most of the verification time (446-frame corridor,
    # sequential pairs: 61 -> 38 CPU-s at 30, same verified pairs and inliers within 0.02 %).
    # Session 19: 10 (alone: matching 73 -> 62 CPU-s, same accuracy, idle machine; with the
    # contrast threshold 0.01, above).
    verify_min_trials: int = 10
    max_h_inlier_ratio: float = 0.8  # pairs whose homography explains more are called planar
    # ... with the global mapper: planar only when a homography explains strictly more matches
    # than the essential matrix. GLOMAP takes each pair's relative pose from its stored model, and
    # a homography's decomposition is degrees off (bend.py); with 0.8 nearly every pair of a
    # corridor flight is planar and its models came out 2.1 % (124 kept frames) and 8.5 % (446)
    # ATE, accepted by the guard; with 1.0, 0.135 % and 0.159 % (docs/sfm.md "Session 17").
    global_max_h_inlier_ratio: float = 1.0
    # --- mapping ---
    min_num_matches: int = 15  # verified matches for a pair to count in mapping
    # Pixel thresholds sized for 160x160 frames. COLMAP's defaults (4 px reprojection, 12 px
    # absolute pose, 2 deg triangulation) are sized for megapixel images; on a 160-px frame they
    # are 2-5 % of the image, admit wrong 2D-3D matches and let a model started from a
    # near-planar pair settle in a bent solution (simulated corridor: ATE 10 % -> 0.1 %).
    max_reproj_error: float = 1.5  # px: point filtering, track merging/completion, init pair
    abs_pose_max_error: float = 2.0  # px: RANSAC threshold when registering a frame (PnP)
    tri_max_angle_error: float = 1.0  # deg: triangulation; re-triangulation gets twice this
    # initial pair: our choice prefers pairs with this many (COLMAP relaxes it when it fails)
    init_min_num_inliers: int = 50
    abs_pose_min_num_inliers: int = 15  # 2D-3D inliers needed to register a frame
    max_models: int = 10  # COLMAP keeps starting new models up to this many
    init_trials: int = 1  # 2: also map from COLMAP's own initial pair, keep the better model
    init_max_gap: int = 10  # our initial pair: at most this many frames apart (no loop twins)
    init_min_tri_angle: float = 8.0  # deg: median triangulation angle of an initial pair
    # |z| of an initial pair's unit relative translation above which the mapper refuses it
    # (COLMAP's default); our pair choice skips such pairs (forward flight down a corridor)
    init_max_forward_motion: float = 0.95
    # Bundle adjustment for video (a flight is a sequence: local BA does most of the work).
    # COLMAP re-adjusts the whole model whenever it grew by 10 % (ratio 1.1), refines global BA
    # up to 5 times and local BA twice; at 1.5 / 1 / 1 / 20 iterations the 446-frame corridor
    # keeps ATE 0.21 %, step rotation max 0.25 deg (docs/sfm.md "Long flights").
    ba_global_ratio: float = 1.5  # global BA when frames or points grew by this factor
    ba_global_max_iterations: int = 20  # solver iterations of one global BA (-1: COLMAP's)
    ba_refinements: int = 1  # BA + re-triangulation rounds, global and local (COLMAP 5 / 2)
    ba_local_images: int = 6  # frames in a local bundle adjustment (COLMAP's default 6)
    ba_local_max_iterations: int = -1  # solver iterations of one local BA (-1: COLMAP's)
    # global BA skips points that add no coverage of their frames (COLMAP's pruning option)
    ba_prune_redundant: bool = False
    # "incremental" (COLMAP's incremental mapper) or "global" (GLOMAP, guarded: a bent or
    # incomplete global model is replaced by the incremental one; sfm/global_map.py)
    mapper: str = "incremental"
    # A single flight of more usable frames than chunk_above is mapped in chunks of
    # chunk_frames frames overlapping by chunk_overlap, merged and bundle-adjusted once
    # (sfm/chunks.py, docs/sfm.md "Chunked mapping"); 0: never. 300: at 223 frames two chunks
    # cost more mapping CPU than one model (35 vs 26 s), at 446 four chunks half (104 vs 208 s).
    chunk_above: int = 300
    chunk_frames: int = 150
    chunk_overlap: int = 40
    # iterations of the merged model's bundle adjustment after triangulating its points again
    # from the database; 0: neither, the merged model keeps the chunks' own points
    # (chunks.keep_chunk_points). The chunks' poses are already good: on the 446-frame
    # corridor 1 / 4 / 10 iterations gave ATE 0.197 / 0.189 / 0.188 % (session 13), and in one
    # run of session 19 (idle machine) 4 iterations 0.200 % / 0.37 deg against 0's 0.214 % /
    # 0.30 deg, mapping 51 -> 24 s wall, the whole sfm 111 -> 84 s (docs/sfm.md "Session 19").
    chunk_ba_iterations: int = 0
    # A single flight of at least keyframes_above usable frames maps its keyframes only: the
    # next keyframe is the furthest frame (within `overlap`) whose matches moved at most
    # keyframe_flow px from the last; the other frames are then registered into their model
    # without bundle adjustment (sfm/keyframes.py); keyframe_flow 0: every frame is mapped.
    # The 3901-frame flight (`simulate --frames 17500`, consecutive frames 0.39 px apart):
    # 449 keyframes, mapping 79 s in all, ATE 0.27 % (docs/sfm.md "Session 20").
    keyframe_flow: float = 2.0
    keyframes_above: int = 300
    # Bundle adjustment inside the chunks' mappers (the merged model's final adjustment
    # couples them): global BA when the chunk grew 3x (not 1.5x), at most 10 iterations,
    # redundant points skipped. Session 14, a 141-frame chunk of the 446-frame corridor mapped
    # from its pair: 23.2 -> 13.6 CPU-s, chunk ATE 0.228 -> 0.215 %; another chunk 19.7 -> 12.7,
    # 0.217 -> 0.194 % (docs/sfm.md "Session 14"). Unchunked flights keep ba_global_*.
    chunk_ba_global_ratio: float = 3.0
    chunk_ba_global_max_iterations: int = 10
    chunk_ba_prune_redundant: bool = True
    # chunks mapped at once: the chunks after the start chunk and those before it are two
    # independent chains (each chunk resumes from its neighbour), mapped in two threads with
    # half the cores each, all of them for a chunk started once the other chain has ended
    # (since session 14); 1: one after another
    chunk_workers: int = 2
    time_cap: float = 0.0  # s: stop mapping after this long and keep the model so far (0: none)
    extend: bool = True  # resume mapping from the largest model to absorb the others
    seed: int = 0  # random seed of the mapper (deterministic runs)
    num_threads: int = -1  # -1: all cores
    # --- retries and acceptance ---
    retry_below: float = 0.9  # registered fraction under which the next remedy is tried
    retry_budget: float = 600.0  # s: no new remedy starts after this much time on retries
    min_registration: float = 0.5  # fail (exit 1) when fewer frames than this fraction register
    prior_fallback: bool = False  # frames that fail to register get their telemetry prior pose

    def validate(self) -> None:
        """Raise ValueError naming the first impossible setting."""
        if self.camera not in CAMERA_MODES:
            raise ValueError(f"camera must be one of {CAMERA_MODES}, got {self.camera!r}")
        if not 0.0 <= self.retry_below <= 1.0 or self.retry_budget < 0:
            raise ValueError("retry_below must be in [0, 1] and retry_budget >= 0")
        if self.init_max_gap < 1 or not 0 < self.init_min_tri_angle < 90:
            raise ValueError("init_max_gap must be >= 1 and init_min_tri_angle in (0, 90) deg")
        if not 0 < self.init_max_forward_motion <= 1:
            raise ValueError("init_max_forward_motion must be in (0, 1]")
        if self.loop_pairs not in LOOP_PAIRS or self.mapper not in MAPPERS:
            raise ValueError(f"loop_pairs must be one of {LOOP_PAIRS}, mapper one of {MAPPERS}")
        if self.keyframe_flow < 0:
            raise ValueError(f"keyframe_flow must be >= 0 px, got {self.keyframe_flow}")
        if self.ba_local_images < 2:
            raise ValueError(f"ba_local_images must be at least 2, got {self.ba_local_images}")
        if self.matcher not in MATCHERS:
            raise ValueError(f"matcher must be one of {MATCHERS}, got {self.matcher!r}")
        if min(self.peak_threshold, self.finer_peak_threshold) <= 0:
            raise ValueError("peak_threshold and finer_peak_threshold must be > 0")
        if self.max_features < 16:
            raise ValueError(f"max_features must be at least 16, got {self.max_features}")
        if self.overlap < 1:
            raise ValueError(f"overlap must be at least 1, got {self.overlap}")
        if not 0.0 <= self.min_registration <= 1.0:
            raise ValueError(f"min_registration must be in [0, 1], got {self.min_registration}")
        if min(self.loop_period, self.loop_num_images, self.cross_num_images) < 1:
            raise ValueError("loop_period, loop_num_images and cross_num_images must be >= 1")
        if self.ray_piece_frames < 2:
            raise ValueError(f"ray_piece_frames must be at least 2, got {self.ray_piece_frames}")
        if self.visual_words < 16:
            raise ValueError(f"visual_words must be at least 16, got {self.visual_words}")
        if min(self.ba_global_ratio, self.chunk_ba_global_ratio) <= 1.0:
            raise ValueError("ba_global_ratio and chunk_ba_global_ratio must be > 1")
        if self.ba_refinements < 1 or self.time_cap < 0:
            raise ValueError("ba_refinements must be >= 1 and time_cap >= 0")
        if self.chunk_above < 0 or not 1 <= self.chunk_overlap < self.chunk_frames / 2:
            raise ValueError("chunk_above must be >= 0 and chunk_overlap in [1, chunk_frames / 2)")
        if min(self.chunk_workers, self.verify_min_trials) < 1 or self.chunk_ba_iterations < 0:
            raise ValueError("chunk_workers, verify_min_trials >= 1 and chunk_ba_iterations >= 0")
        if min(self.max_reproj_error, self.abs_pose_max_error, self.tri_max_angle_error) <= 0:
            raise ValueError("reprojection, absolute-pose and angle thresholds must be > 0")

    def chunked(self, n_frames: int, n_drones: int) -> bool:
        """Whether ``n_drones`` flights of ``n_frames`` usable frames in all are mapped in
        chunks: one flight only (a swarm's flights share no chunk frames), long enough."""
        return n_drones == 1 and 0 < self.chunk_above < n_frames

    def for_chunks(self) -> SfmOptions:
        """These options with the chunks' own bundle adjustment (``chunk_ba_*``) as the
        mapper's global bundle adjustment."""
        return replace(
            self,
            ba_global_ratio=self.chunk_ba_global_ratio,
            ba_global_max_iterations=self.chunk_ba_global_max_iterations,
            ba_prune_redundant=self.chunk_ba_prune_redundant,
        )

    def resolved_matcher(self, n_frames: int) -> str:
        """ "sequential" or "exhaustive" for a flight of ``n_frames`` frames."""
        if self.matcher != "auto":
            return self.matcher
        return "exhaustive" if n_frames < self.exhaustive_below else "sequential"

    def resolved_max_h_ratio(self) -> float:
        """The homography share above which two-view verification labels a pair planar."""
        if self.mapper == "global":
            return self.global_max_h_inlier_ratio
        return self.max_h_inlier_ratio

    def to_dict(self) -> dict[str, Any]:
        """JSON-able copy (stored in provenance and the report)."""
        return asdict(self)
