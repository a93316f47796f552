"""The COLMAP phases on pycolmap: SIFT extraction, matching (with a home-made loop index), mapping.

Each function works on files (an image folder, a COLMAP database, model folders) so that the
whole sequence can run in a child process (:mod:`dronecap.sfm.isolate`): a COLMAP ``CHECK``
failure aborts its process, and it must never take the caller down with it.

Loop detection never touches pycolmap's default vocabulary tree (offline, the attempt to download
it aborts the process): :func:`build_visual_index` builds a small index from the flight's own
descriptors and the sequential matcher is pointed at that file.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

from dronecap.sfm.flights import flight_of
from dronecap.sfm.options import FINEST_OCTAVE, SfmOptions
from dronecap.sfm.retrieval import write_cross_flight_pairs

TRAIN_DESCRIPTORS = 20000  # descriptors sampled to train the flight's visual vocabulary
MIN_KEYPOINTS = 16  # a frame with fewer SIFT keypoints cannot register (reported as textureless)


def extract(
    database: Path,
    image_dir: Path,
    names: list[str],
    opts: SfmOptions,
    cameras: list[tuple[str, list[float]] | None],
) -> dict[str, int]:
    """SIFT on CPU into ``database``: one camera shared by every image, or for a swarm (names
    in a folder per drone, ``reconstruct.image_names``) one camera per folder.

    Args:
        cameras: per drone, (COLMAP model name, params) when intrinsics are known (params in
            COLMAP's pixel convention), or None to let COLMAP guess a SIMPLE_RADIAL camera from
            the image size.

    Returns:
        image name -> number of keypoints.
    """
    import pycolmap

    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = "SIMPLE_RADIAL"
    if len(cameras) == 1 and cameras[0] is not None:
        reader.camera_model = cameras[0][0]
        reader.camera_params = ",".join(f"{v:.10g}" for v in cameras[0][1])
    mode = pycolmap.CameraMode.SINGLE if len(cameras) == 1 else pycolmap.CameraMode.PER_FOLDER
    ext = pycolmap.FeatureExtractionOptions()
    ext.num_threads = opts.num_threads
    ext.sift.max_num_features = opts.max_features
    ext.sift.first_octave = opts.first_octave
    ext.sift.peak_threshold = opts.peak_threshold
    pycolmap.extract_features(
        database,
        image_dir,
        image_names=names,
        camera_mode=mode,
        reader_options=reader,
        extraction_options=ext,
        device=pycolmap.Device.cpu,
    )
    with pycolmap.Database.open(database) as db:
        if len(cameras) > 1:
            _set_folder_cameras(db, cameras)
        return {im.name: db.num_keypoints_for_image(im.image_id) for im in db.read_all_images()}


def _set_folder_cameras(db: Any, cameras: list[tuple[str, list[float]] | None]) -> None:
    """Give each drone's folder camera its known model and parameters (``cameras`` per drone;
    None: COLMAP's guess stays)."""
    import pycolmap

    done: set[int] = set()
    for im in db.read_all_images():
        known = cameras[flight_of(im.name)]
        if known is None or im.camera_id in done:
            continue
        old = db.read_camera(im.camera_id)
        cam = pycolmap.Camera(
            model=known[0],
            width=old.width,
            height=old.height,
            params=np.asarray(known[1], np.float64),
            camera_id=im.camera_id,
        )
        cam.has_prior_focal_length = True
        db.update_camera(cam)
        done.add(im.camera_id)


def extract_finer_when_sparse(
    database: Path,
    image_dir: Path,
    names: list[str],
    opts: SfmOptions,
    cameras: list[tuple[str, list[float]] | None],
) -> tuple[dict[str, int], int]:
    """:func:`extract` at ``opts.first_octave``; when the frames' median keypoint count is
    under ``opts.finer_below``, the database is built again one octave finer (never finer
    than :data:`FINEST_OCTAVE`).

    Returns:
        (image name -> number of keypoints, the first octave the database holds).
    """
    octave = opts.first_octave
    keypoints = extract(database, image_dir, names, opts, cameras)
    median = float(np.median(list(keypoints.values()))) if keypoints else 0.0
    if octave > FINEST_OCTAVE and median < opts.finer_below:
        database.unlink()
        octave -= 1
        finer = dataclasses.replace(opts, first_octave=octave)
        keypoints = extract(database, image_dir, names, finer, cameras)
    return keypoints, octave


def build_visual_index(database: Path, out_file: Path, opts: SfmOptions) -> int:
    """Write a visual index (vocabulary + inverted file) of the flight's own SIFT descriptors.

    The vocabulary is trained on at most TRAIN_DESCRIPTORS sampled descriptors and has at most
    ``opts.visual_words`` words, at most one per 40 training descriptors (k-means needs several
    samples per centre); every descriptor is then indexed. Returns the number of words.
    """
    import pycolmap

    with pycolmap.Database.open(database) as db:
        images = [im for im in db.read_all_images() if db.num_keypoints_for_image(im.image_id)]
        descs = {im.image_id: db.read_descriptors(im.image_id).to_float() for im in images}
        kpts = {im.image_id: _keypoints(db.read_keypoints(im.image_id)) for im in images}
    stacked = np.concatenate([d.data for d in descs.values()]).astype(np.float32)
    if len(stacked) > TRAIN_DESCRIPTORS:  # k-means time grows with the sample; words need ~40
        pick = np.random.default_rng(opts.seed).choice(len(stacked), TRAIN_DESCRIPTORS, False)
        stacked = stacked[np.sort(pick)]
    words = int(max(16, min(opts.visual_words, 2 ** int(np.log2(max(len(stacked) // 40, 16))))))
    index = pycolmap.VisualIndex.create(128, 64)
    build = pycolmap.VisualIndex.BuildOptions()
    build.num_visual_words = words
    build.num_threads = opts.num_threads
    build.num_iterations = 30
    sift = pycolmap.FeatureExtractorType.SIFT
    index.build(build, pycolmap.FeatureDescriptorsFloat(sift, stacked))
    add = pycolmap.VisualIndex.IndexOptions()
    add.num_threads = opts.num_threads
    for image_id, desc in descs.items():
        index.add(add, image_id, kpts[image_id], desc)
    index.prepare()
    index.write(out_file)
    return words


def _keypoints(rows: np.ndarray) -> Any:
    """COLMAP keypoint table [K, 6] (x, y, a11, a12, a21, a22) -> pycolmap.FeatureKeypoints."""
    import pycolmap

    keys = ("x", "y", "a11", "a12", "a21", "a22")
    return pycolmap.FeatureKeypoints(
        [pycolmap.FeatureKeypoint(**dict(zip(keys, map(float, r), strict=True))) for r in rows]
    )


def match(
    database: Path,
    work: Path,
    opts: SfmOptions,
    n_frames: int,
    swarm: bool = False,
    own_pairs: bool = True,
) -> dict[str, Any]:
    """Match and geometrically verify image pairs; returns what was done (for the report).

    ``swarm`` (several drones' flights): after the flights' own pairs, every frame is also
    matched with the ``opts.cross_num_images`` most alike frames of the other drones' flights
    (:mod:`dronecap.sfm.retrieval`): the pairs that link one drone's flight to another's.
    ``own_pairs`` False: the flights' own pairs are matched already (:mod:`ray_front`).
    """
    import pycolmap

    kind = opts.resolved_matcher(n_frames)
    info: dict[str, Any] = {"matcher": kind}
    matching = pycolmap.FeatureMatchingOptions()
    matching.num_threads = opts.num_threads
    verify = pycolmap.TwoViewGeometryOptions()
    verify.ransac.max_error = opts.max_epipolar_error
    verify.max_H_inlier_ratio = opts.max_h_inlier_ratio
    common = {"matching_options": matching, "verification_options": verify}
    if not own_pairs:
        info["matcher"] = "per flight (Ray tasks)"
    elif kind == "exhaustive":
        pycolmap.match_exhaustive(database, **common, device=pycolmap.Device.cpu)
    else:
        pairing = pycolmap.SequentialPairingOptions()
        pairing.overlap = opts.overlap
        pairing.quadratic_overlap = opts.quadratic_overlap
        pairing.num_threads = opts.num_threads
        use_loops = opts.loop_detection and n_frames > opts.overlap + 1
        if use_loops:
            t = time.perf_counter()
            index_file = work / "visual_index.bin"
            info["visual_words"] = build_visual_index(database, index_file, opts)
            info["index_seconds"] = round(time.perf_counter() - t, 3)
            pairing.loop_detection = True
            pairing.loop_detection_period = opts.loop_period
            pairing.loop_detection_num_images = opts.loop_num_images
            pairing.vocab_tree_path = str(index_file)  # never the default: it downloads
        info["loop_detection"] = use_loops
        pycolmap.match_sequential(
            database, **common, pairing_options=pairing, device=pycolmap.Device.cpu
        )
    if swarm and (kind != "exhaustive" or not own_pairs):  # exhaustive has every pair
        t = time.perf_counter()
        pair_file = work / "cross_flight_pairs.txt"
        n_pairs = write_cross_flight_pairs(database, pair_file, opts.cross_num_images, opts.seed)
        imported = pycolmap.ImportedPairingOptions()
        imported.match_list_path = str(pair_file)
        pycolmap.match_image_pairs(
            database, **common, pairing_options=imported, device=pycolmap.Device.cpu
        )
        info["cross_flight_pairs"] = n_pairs
        info["cross_flight_seconds"] = round(time.perf_counter() - t, 3)
    with pycolmap.Database.open(database) as db:
        info["matched_pairs"] = db.num_matched_image_pairs()
        info["verified_pairs"] = db.num_verified_image_pairs()
        pair_ids, geoms = db.read_two_view_geometries()
        names = {im.image_id: im.name for im in db.read_all_images()}
    linked: dict[str, int] = dict.fromkeys(names.values(), 0)
    for pair_id, g in zip(pair_ids, geoms, strict=True):
        if g.inlier_matches.shape[0] >= opts.min_num_matches:
            a, b = pycolmap.pair_id_to_image_pair(pair_id)
            linked[names[a]] += 1
            linked[names[b]] += 1
    info["verified_partners"] = linked
    return info


def mapper_options(opts: SfmOptions, refine_camera: bool, relaxed: bool = False) -> Any:
    """IncrementalPipelineOptions for small gray frames; ``relaxed`` for the extension pass.

    ``refine_camera``: bundle adjustment and registration refine the focal length(s) and the
    distortion (``--camera refine|estimate``); the principal point is never refined.
    """
    import pycolmap

    m = pycolmap.IncrementalPipelineOptions()
    m.min_num_matches = opts.min_num_matches
    m.max_num_models = opts.max_models
    m.min_model_size = 3
    m.num_threads = opts.num_threads
    m.random_seed = opts.seed
    m.extract_colors = True  # the points' colours go into points.ply
    m.ba_global_frames_ratio = m.ba_global_points_ratio = opts.ba_global_ratio
    m.ba_global_max_num_iterations = opts.ba_global_max_iterations
    m.ba_global_max_refinements = m.ba_local_max_refinements = opts.ba_refinements
    if opts.time_cap > 0:
        m.max_runtime_seconds = int(np.ceil(opts.time_cap))
    m.ba_refine_focal_length = refine_camera
    m.ba_refine_extra_params = refine_camera
    m.ba_refine_principal_point = False
    m.mapper.init_min_num_inliers = opts.init_min_num_inliers
    m.mapper.init_min_tri_angle = opts.init_min_tri_angle
    m.mapper.init_max_forward_motion = opts.init_max_forward_motion
    m.mapper.abs_pose_min_num_inliers = opts.abs_pose_min_num_inliers
    m.mapper.abs_pose_refine_focal_length = refine_camera
    m.mapper.abs_pose_refine_extra_params = refine_camera
    m.mapper.random_seed = opts.seed
    m.mapper.init_max_error = opts.max_reproj_error
    m.mapper.filter_max_reproj_error = opts.max_reproj_error
    m.mapper.abs_pose_max_error = opts.abs_pose_max_error
    m.triangulation.merge_max_reproj_error = opts.max_reproj_error
    m.triangulation.complete_max_reproj_error = opts.max_reproj_error
    m.triangulation.create_max_angle_error = opts.tri_max_angle_error
    m.triangulation.continue_max_angle_error = opts.tri_max_angle_error
    m.triangulation.re_max_angle_error = 2.0 * opts.tri_max_angle_error
    if relaxed:
        m.multiple_models = False
        m.mapper.abs_pose_min_num_inliers = max(8, opts.abs_pose_min_num_inliers // 2)
        m.mapper.abs_pose_min_inlier_ratio = 0.15
        m.mapper.max_reg_trials = 6
    return m


def incremental_map(
    database: Path,
    image_dir: Path,
    out_dir: Path,
    opts: SfmOptions,
    refine_camera: bool,
    on_register: Callable[[int], None],
    input_path: Path | None = None,
    init_pair: tuple[int, int] | None = None,
    image_names: list[str] | None = None,
) -> dict[str, dict[str, float]]:
    """Run COLMAP's incremental mapper; writes models to ``out_dir/<k>``.

    Args:
        on_register: called with the number of frames just registered (2 for the initial pair,
            then 1 per frame) so that a progress bar can follow.
        input_path: resume from this model (extension pass, relaxed registration thresholds).
        init_pair: database image ids of the initial pair (default: COLMAP chooses). One model
            only: COLMAP would start every further model from the same pair.
        image_names: map only these images (default: all).

    Returns:
        model folder -> {"frames": registered frames, "reproj": mean reprojection error, px}.
    """
    import pycolmap

    out_dir.mkdir(parents=True, exist_ok=True)
    options = mapper_options(opts, refine_camera, relaxed=input_path is not None)
    if init_pair is not None:
        options.init_image_id1, options.init_image_id2 = init_pair
        options.multiple_models = False
    if image_names is not None:
        options.image_names = image_names
    models = pycolmap.incremental_mapping(
        database,
        image_dir,
        out_dir,
        options,
        input_path=str(input_path) if input_path is not None else "",
        initial_image_pair_callback=lambda: on_register(2),
        next_image_callback=lambda: on_register(1),
    )
    found = {}
    for k, rec in models.items():
        (out_dir / str(k)).mkdir(exist_ok=True)
        rec.write(out_dir / str(k))  # the pipeline does not write every model itself
        found[str(out_dir / str(k))] = {
            "frames": rec.num_reg_images(),
            "reproj": float(rec.compute_mean_reprojection_error()),
        }
    return found


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
            measured = _measure_planar(db, images, pair_ids, geoms, rank, opts, min_gap)
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
    pair_ids: Any,
    geoms: list[Any],
    rank: dict[int, int],
    opts: SfmOptions,
    min_gap: int,
) -> list[PairCandidate]:
    """Measure planar / panoramic pairs ``min_gap`` to ``opts.init_max_gap`` frames apart, the
    widest gap first (most inliers among equals): the fallback when no general epipolar pair
    is a start COLMAP accepts.

    Why: in a slow flight (the 1954-frame corridor, 446 kept frames) all 4495 verified pairs
    are labelled planar-or-panoramic, so :func:`initial_pairs` has no candidate and COLMAP's
    own search ran for 1116 s and built a bent model (ATE 2.9 %); the widest pair, 10 frames
    apart at a 3 deg triangulation angle, starts a straight model (ATE 0.21 %).
    """
    pool = []
    for pair_id, g in zip(pair_ids, geoms, strict=True):
        a, b = _pair_images(pair_id)
        gap = abs(rank[a] - rank[b])
        if min_gap <= gap <= opts.init_max_gap and g.inlier_matches.shape[0] > 0:
            pool.append((gap, g.inlier_matches.shape[0], a, b, g))
    pool.sort(key=lambda c: (-c[0], -c[1]))
    return [_measure_pair(db, images, n, a, b, g) for _, n, a, b, g in pool[:INIT_CANDIDATES]]


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
