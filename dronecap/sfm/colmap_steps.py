"""The COLMAP phases on pycolmap after SIFT (:mod:`dronecap.sfm.features`): matching (with a
home-made loop index) and mapping.

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
from typing import Any

import numpy as np

from dronecap.sfm.initial_pair import FALLBACK_MIN_ANGLE
from dronecap.sfm.options import SfmOptions
from dronecap.sfm.retrieval import write_cross_flight_pairs, write_loop_pairs

# Two chunk chains (sfm/chunks.py, two threads) opening one COLMAP database at the same
# moment made one open fail once in the test suite at load 3 ("No registered database factory
# succeeded"; the cause inside COLMAP is not known). The chains now open copies of their own;
# the mapper still retries such a failed open this often, in case the cause is not the file.
OPEN_ATTEMPTS = 3

TRAIN_DESCRIPTORS = 20000  # descriptors sampled to train the flight's visual vocabulary
PAIR_TRIES = 3  # our initial pairs tried in turn (best first) until one starts a non-tiny model
NARROW_PAIR_MARGIN = 0.8  # a pair under init_min_tri_angle starts with this x its measured angle


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
    common = matching_options(opts)
    if not own_pairs:
        info["matcher"] = "pieces of flights (Ray tasks)"
    elif kind == "exhaustive":
        pycolmap.match_exhaustive(database, **common, device=pycolmap.Device.cpu)
    else:
        _match_sequential(database, work, opts, n_frames, common, info)
    if swarm and (kind != "exhaustive" or not own_pairs):  # exhaustive has every pair
        t = time.perf_counter()
        pair_file = work / "cross_flight_pairs.txt"
        n_pairs = write_cross_flight_pairs(database, pair_file, opts.cross_num_images, opts.seed)
        match_listed(database, pair_file, opts)
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


def matching_options(opts: SfmOptions) -> dict[str, Any]:
    """pycolmap's matching and two-view verification options for ``opts`` (keyword
    arguments of its matching functions)."""
    import pycolmap

    matching = pycolmap.FeatureMatchingOptions()
    matching.num_threads = opts.num_threads
    verify = pycolmap.TwoViewGeometryOptions()
    verify.ransac.max_error = opts.max_epipolar_error
    verify.ransac.min_num_trials = opts.verify_min_trials
    verify.max_H_inlier_ratio = opts.resolved_max_h_ratio()
    return {"matching_options": matching, "verification_options": verify}


def verify_again(database: Path, opts: SfmOptions) -> None:
    """Replace the two-view geometry of every matched pair in ``database`` by a new
    verification with ``opts``' thresholds and planar label (:func:`matching_options`); the
    matches stay."""
    import pycolmap

    with pycolmap.Database.open(database) as db:
        db.clear_two_view_geometries()
    verifier = pycolmap.GeometricVerifierOptions()
    verifier.num_threads = opts.num_threads
    verify = matching_options(opts)["verification_options"]
    pycolmap.geometric_verification(database, verifier, two_view_geometry_options=verify)


def match_listed(database: Path, pair_file: Path, opts: SfmOptions) -> None:
    """Match and verify the image pairs listed in ``pair_file`` (a line "name_a name_b" each)
    into ``database``, with :func:`matching_options` of ``opts``; pairs matched before are
    left as they are."""
    import pycolmap

    imported = pycolmap.ImportedPairingOptions()
    imported.match_list_path = str(pair_file)
    pycolmap.match_image_pairs(
        database, **matching_options(opts), pairing_options=imported, device=pycolmap.Device.cpu
    )


def _match_sequential(
    database: Path,
    work: Path,
    opts: SfmOptions,
    n_frames: int,
    common: dict[str, Any],
    info: dict[str, Any],
) -> None:
    """Each frame with its ``opts.overlap`` next ones, plus loop pairs (``opts.loop_pairs``:
    pycolmap's visual index, or our bag of words matched as a pair list afterwards)."""
    import pycolmap

    pairing = pycolmap.SequentialPairingOptions()
    pairing.overlap = opts.overlap
    pairing.quadratic_overlap = opts.quadratic_overlap
    pairing.num_threads = opts.num_threads
    use_loops = opts.loop_detection and opts.loop_pairs != "none" and n_frames > opts.overlap + 1
    t, c = time.perf_counter(), time.process_time()
    if use_loops and opts.loop_pairs == "index":
        index_file = work / "visual_index.bin"
        info["visual_words"] = build_visual_index(database, index_file, opts)
        info["index_seconds"] = round(time.perf_counter() - t, 3)
        info["index_cpu_seconds"] = round(time.process_time() - c, 3)
        pairing.loop_detection = True
        pairing.loop_detection_period = opts.loop_period
        pairing.loop_detection_num_images = opts.loop_num_images
        pairing.vocab_tree_path = str(index_file)  # never the default: it downloads
    info["loop_detection"] = opts.loop_pairs if use_loops else False
    pycolmap.match_sequential(
        database, **common, pairing_options=pairing, device=pycolmap.Device.cpu
    )
    if use_loops and opts.loop_pairs == "words":
        t, c = time.perf_counter(), time.process_time()
        pair_file = work / "loop_pairs.txt"
        info["loop_pairs"] = write_loop_pairs(
            database,
            pair_file,
            opts.loop_period,
            opts.loop_num_images,
            opts.overlap + 1,
            opts.seed,
        )
        match_listed(database, pair_file, opts)
        info["loop_seconds"] = round(time.perf_counter() - t, 3)
        info["loop_cpu_seconds"] = round(time.process_time() - c, 3)


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
    m.mapper.ba_local_num_images = opts.ba_local_images
    m.ba_local_max_num_iterations = opts.ba_local_max_iterations
    m.mapper.ba_global_ignore_redundant_points3D = opts.ba_prune_redundant
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
    seeded: bool = False,
) -> dict[str, dict[str, float]]:
    """Run COLMAP's incremental mapper; writes models to ``out_dir/<k>``.

    Args:
        on_register: called with the number of frames just registered (2 for the initial pair,
            then 1 per frame) so that a progress bar can follow.
        input_path: resume from this model (extension pass, relaxed registration thresholds).
        init_pair: database image ids of the initial pair (default: COLMAP chooses). One model
            only: COLMAP would start every further model from the same pair.
        image_names: map only these images (default: all).
        seeded: ``input_path`` is a seed (:mod:`dronecap.sfm.chunks`): its frames are held
            fixed and registration keeps the normal thresholds.

    Returns:
        model folder -> {"frames": registered frames, "reproj": mean reprojection error, px}.
    """
    import pycolmap

    out_dir.mkdir(parents=True, exist_ok=True)
    options = mapper_options(opts, refine_camera, relaxed=input_path is not None and not seeded)
    options.fix_existing_frames = seeded
    if init_pair is not None:
        options.init_image_id1, options.init_image_id2 = init_pair
        options.multiple_models = False
    if image_names is not None:
        options.image_names = image_names
    for attempt in range(OPEN_ATTEMPTS):
        try:
            models = pycolmap.incremental_mapping(
                database,
                image_dir,
                out_dir,
                options,
                input_path=str(input_path) if input_path is not None else "",
                initial_image_pair_callback=lambda: on_register(2),
                next_image_callback=lambda: on_register(1),
            )
            break
        except RuntimeError as e:  # two chunk chains opening the database at the same moment
            if "database factory" not in str(e) or attempt == OPEN_ATTEMPTS - 1:
                raise
            time.sleep(0.5 * (attempt + 1))
    found = {}
    for k, rec in models.items():  # the pipeline does not write every model itself
        found.update(write_model(rec, out_dir / str(k)))
    return found


def write_model(rec: Any, folder: Path) -> dict[str, dict[str, float]]:
    """Write the reconstruction ``rec`` into ``folder`` (created); returns the models record
    the mappers return: {folder: {"frames": registered, "reproj": mean reprojection px}}."""
    folder.mkdir(parents=True, exist_ok=True)
    rec.write(folder)
    return {
        str(folder): {
            "frames": rec.num_reg_images(),
            "reproj": float(rec.compute_mean_reprojection_error()),
        }
    }


def map_from_pairs(
    database: Path,
    image_dir: Path,
    work: Path,
    opts: SfmOptions,
    refine_camera: bool,
    on_register: Callable[[int], None],
    pairs: list[tuple[tuple[int, int], dict[str, Any]]],
    enough: float,
    only: list[str] | None = None,
) -> tuple[dict[str, dict[str, float]], list[dict[str, Any]]]:
    """Map from our initial ``pairs`` (:func:`initial_pairs`, best first) in turn (only the
    frames ``only``, default all), into
    ``work/models``, ``work/models_pair2``, ..., until one starts a model of at least ``enough``
    frames; at most :data:`PAIR_TRIES` pairs.

    COLMAP refuses some starts (its own checks on the pair, at its own thresholds) and some grow
    no further than a few frames; the next pair is then a better start than COLMAP's own search,
    which favours planar pairs. Returns the models found (folder -> frames, reprojection error)
    and each tried pair's report record with the frames of its model ("model_frames", 0: none).
    """
    found: dict[str, dict[str, float]] = {}
    tried = []
    for k, (pair, record) in enumerate(pairs[:PAIR_TRIES]):
        out = work / ("models" if k == 0 else f"models_pair{k + 1}")
        # COLMAP re-checks the pair's angle: let a narrow pair (a slow flight) through
        angle = max(FALLBACK_MIN_ANGLE, NARROW_PAIR_MARGIN * record["tri_angle_deg"])
        pair_opts = dataclasses.replace(
            opts, init_min_tri_angle=min(opts.init_min_tri_angle, angle)
        )
        models = incremental_map(
            database, image_dir, out, pair_opts, refine_camera, on_register, None, pair, only
        )
        found.update(models)
        tried.append(
            {**record, "model_frames": max((v["frames"] for v in models.values()), default=0)}
        )
        if tried[-1]["model_frames"] >= enough:
            break
    return found, tried
