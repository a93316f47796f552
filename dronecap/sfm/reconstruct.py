"""From frames to a COLMAP model: work folder, isolated COLMAP run with progress, model choice.

:func:`reconstruct` writes the frames as zero-padded PNGs (COLMAP's sequential pairing follows
image *names*), runs :func:`colmap_job` in a child process (:mod:`dronecap.sfm.isolate`) and
loads the chosen model. The child runs extraction, matching and incremental mapping (from our
initial pairs in turn, :func:`map_from_pairs`, then COLMAP's own when ours stay tiny; a long
single flight in chunks, :mod:`dronecap.sfm.chunks`), picks the
largest of the models COLMAP returns (model 0 is not always the largest) and, when frames are
still missing, resumes mapping from it with relaxed registration thresholds so that frames of the
other models can join it; frames whose pose jumps off the flight path
(:func:`dronecap.sfm.report.pose_jumps`) are then deregistered and registered again.
"""

from __future__ import annotations

import dataclasses
import shutil
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from dronecap.sfm.bend import rotation_disagreement
from dronecap.sfm.camera_plan import CameraPlan
from dronecap.sfm.chunks import map_in_chunks
from dronecap.sfm.colmap_steps import incremental_map, map_from_pairs, match, verify_again
from dronecap.sfm.features import MIN_KEYPOINTS, extract_finer_when_sparse
from dronecap.sfm.flights import image_names
from dronecap.sfm.isolate import run_isolated
from dronecap.sfm.keyframes import REST, choose_keyframes, register_rest
from dronecap.sfm.links import separate_unlinked
from dronecap.sfm.options import SfmOptions
from dronecap.sfm.repair import jump_frames, refine_camera_of, remap_jumps
from dronecap.sfm.wide_pairs import start_pairs

GLOBAL_MIN_FRACTION = 0.99  # a global model is kept only with this share of the usable frames
TINY_MODEL = 0.5  # our start registered under this fraction of usable frames: also try COLMAP's
ALT_MODELS = "models_alt"  # folder of the models COLMAP started from its own initial pair
NO_START = (
    "the mapper found no initial pair with enough inliers and baseline"
    " (a camera turning in place or hovering gives no baseline)"
)


def colmap_job(
    emit: Callable[[tuple[Any, ...]], None],
    work: str,
    names: list[str],
    options: dict[str, Any],
    cameras: list[tuple[str, list[float]] | None],
    refine_camera: bool,
    refine_after: bool = False,
) -> dict[str, Any]:
    """Child-process body: extract, match, map, extend. Returns a JSON-able summary.

    ``cameras``: per drone (image folder, :func:`image_names`), (COLMAP model, params) to start
    from, or None (COLMAP guesses camera_plan.ESTIMATE_MODEL);
    ``refine_camera``: whether mapping refines focal length and distortion; ``refine_after``:
    whether a final bundle adjustment of the chosen model refines them (principal point fixed).

    Emits ("phase", name, registered_so_far) when a phase starts and ("registered", k) when the
    mapper registers k more frames. The summary holds per-image keypoints, matching info,
    model sizes, the chosen model's folder ("best", or None) and seconds per phase.
    """
    opts = SfmOptions(**options)
    deadline = time.perf_counter() + opts.time_cap if opts.time_cap > 0 else None
    root = Path(work)
    db, images = root / "database.db", root / "images"
    times: dict[str, float] = {}
    cpu: dict[str, float] = {}  # CPU seconds (all threads of this process) per phase
    out: dict[str, Any] = {"times": times, "cpu": cpu, "models": {}, "best": None, "stopped": None}
    last = [None, time.process_time()]

    def phase(name: str, registered: int = 0) -> float:
        _cpu_since(cpu, last, name)
        emit(("phase", name, registered))
        return time.perf_counter()

    n_drones = len(cameras)
    usable = _front_end(out, root, names, opts, cameras, phase)
    if usable is None:
        return out

    def on_register(k: int) -> None:
        emit(("registered", k))

    mapped = _keyframes(out, root, usable, opts, n_drones, phase)
    opts = _capped(opts, deadline)
    found = {}
    if opts.mapper == "global":
        t = phase("map global")
        found = _global_first(out, root, opts, refine_camera, len(usable))
        times["map_global"] = time.perf_counter() - t
    if not found and opts.chunked(len(usable), n_drones):  # a long flight's keyframes too
        t = phase("map chunks")
        found = map_in_chunks(out, root, mapped, opts, refine_camera, on_register, TINY_MODEL)
        times["map_chunks"] = time.perf_counter() - t
    if not found:
        found = _incremental(out, root, opts, refine_camera, on_register, mapped, deadline, phase)
    if found and len(mapped) < len(usable):
        found = _register_rest(out, root, found, usable, opts, refine_camera, on_register, phase)
    out["models"] = {str(Path(k).relative_to(root)): v for k, v in found.items()}
    if not found:
        out["stopped"] = NO_START
        return out
    size = _settle(
        out, found, root, names, len(usable), opts, refine_camera, deadline, phase, on_register
    )
    if n_drones > 1:
        t = phase("separate unlinked flights", size)
        out["best"], out["flights"] = separate_unlinked(
            db, images, root, Path(out["best"]), names, n_drones, opts, refine_camera, on_register
        )
        times["unlinked"] = time.perf_counter() - t
    t = phase("bend check", size)
    out["bend_check"] = rotation_disagreement(db, Path(out["best"]), threads=opts.num_threads)
    times["bend_check"] = time.perf_counter() - t
    if refine_after:
        t = phase("refine camera", size)
        out["best"] = refine_camera_of(Path(out["best"]), root / "refined", refine_camera)
        times["refine_camera"] = time.perf_counter() - t
    _cpu_since(cpu, last, None)
    return out


def _cpu_since(cpu: dict[str, float], last: list[Any], name: str | None) -> None:
    """Add the CPU seconds since ``last`` = [phase, process_time] to that phase in ``cpu``;
    ``name`` is the phase starting now (None: the end)."""
    now = time.process_time()
    if last[0] is not None:
        cpu[last[0]] = round(cpu.get(last[0], 0.0) + now - last[1], 3)
    last[0], last[1] = name, now


def _keyframes(
    out: dict[str, Any],
    root: Path,
    usable: list[str],
    opts: SfmOptions,
    n_drones: int,
    phase: Callable[..., float],
) -> list[str]:
    """The frames the mapper maps: a long single flight's keyframes (:mod:`keyframes`, record in
    ``out["keyframes"]``), else all ``usable`` frames."""
    thin = opts.keyframe_flow > 0 and n_drones == 1 and opts.mapper != "global"
    if not thin or len(usable) < opts.keyframes_above:
        return usable
    t = phase("keyframes")
    mapped, out["keyframes"] = choose_keyframes(root / "database.db", root, usable, opts)
    out["times"]["keyframes"] = time.perf_counter() - t
    return mapped


def _register_rest(
    out: dict[str, Any],
    root: Path,
    found: dict[str, dict[str, float]],
    usable: list[str],
    opts: SfmOptions,
    refine_camera: bool,
    on_register: Callable[[int], None],
    phase: Callable[..., float],
) -> dict[str, dict[str, float]]:
    """The keyframes' best model among ``found`` with every other ``usable`` frame registered
    into it (:func:`dronecap.sfm.keyframes.register_rest`)."""
    best = _best(found)
    t = phase("register the other frames", found[best]["frames"])
    db = root / "database.db"
    found = register_rest(db, Path(best), root / REST, usable, opts, refine_camera, on_register)
    out["times"]["register_rest"] = time.perf_counter() - t
    return found


def _global_first(
    out: dict[str, Any], root: Path, opts: SfmOptions, refine_camera: bool, n_usable: int
) -> dict[str, dict[str, float]]:
    """GLOMAP's models when the guard accepts them (:mod:`global_map`), else {}; the guard's
    record goes to ``out["global_mapper"]``."""
    from dronecap.sfm.global_map import accept, global_map

    found, record = global_map(
        root / "database.db", root / "images", root / "global", opts, refine_camera
    )
    record["kept"] = accept(record, n_usable, GLOBAL_MIN_FRACTION)
    out["global_mapper"] = record
    out["init_pair"] = {"tried": [], "chosen": None}
    if record["kept"]:
        return found
    # the incremental mapper gets its own labels back: from the global mapper's (fewer pairs
    # planar) it mapped the 89-frame corridor bent (ATE 8-12 %) in 4 runs of 6, unflagged
    verify_again(root / "database.db", dataclasses.replace(opts, mapper="incremental"))
    return {}


def _incremental(
    out: dict[str, Any],
    root: Path,
    opts: SfmOptions,
    refine_camera: bool,
    on_register: Callable[[int], None],
    usable: list[str],
    deadline: float | None,
    phase: Callable[..., float],
) -> dict[str, dict[str, float]]:
    """Incremental mapping of the ``usable`` frames from our initial pairs (wide pairs matched
    for them when the flight's own are too narrow: :mod:`wide_pairs`), then from COLMAP's own
    start when ours stays tiny (or ``opts.init_trials`` > 1). Returns the models found; fills
    ``out``'s init_pair, times and, when the time cap passed, stopped."""
    db, images, times = root / "database.db", root / "images", out["times"]
    t = phase("map")
    pairs, info = start_pairs(db, root, opts, usable)
    enough = TINY_MODEL * len(usable)
    found, tried = map_from_pairs(
        db, images, root, opts, refine_camera, on_register, pairs, enough, usable
    )
    out["init_pair"] = {
        **info,
        "tried": tried,
        "chosen": max(tried, key=lambda r: r["model_frames"], default=None),
    }
    times["map"] = time.perf_counter() - t
    ours = max((v["frames"] for v in found.values()), default=0)
    if _out_of_time(deadline):
        out["stopped"] = "time cap reached: the model so far is kept (not complete)"
    elif ours < enough or opts.init_trials > 1:  # COLMAP's own start as well
        opts = _capped(opts, deadline)
        t = phase("map (colmap start)")
        alt = incremental_map(
            db, images, root / ALT_MODELS, opts, refine_camera, on_register, image_names=usable
        )
        times["map_colmap_start"] = time.perf_counter() - t
        found.update(alt)
    return found


def _front_end(
    out: dict[str, Any],
    root: Path,
    names: list[str],
    opts: SfmOptions,
    cameras: list[tuple[str, list[float]] | None],
    phase: Callable[..., float],
) -> list[str] | None:
    """Extract and match into ``root``'s database (features and sequential pairs of the
    flights' pieces on Ray with ``opts.ray``: :mod:`dronecap.sfm.ray_front`), filling
    ``out``'s keypoints, first_octave, match and times. Returns the frames with enough
    keypoints, or None after setting ``out["stopped"]``."""
    db, images, times = root / "database.db", root / "images", out["times"]
    on_ray = bool(opts.ray)
    t = phase("extract + sequential pairs on Ray" if on_ray else "extract")
    if on_ray:
        from dronecap.sfm.ray_front import front_end_on_ray

        out["keypoints"], out["first_octave"], ray_info = front_end_on_ray(
            db, images, names, opts, cameras
        )
    else:
        out["keypoints"], out["first_octave"] = extract_finer_when_sparse(
            db, images, names, opts, cameras
        )
    times["extract"] = time.perf_counter() - t
    usable = [n for n in names if out["keypoints"].get(n, 0) >= MIN_KEYPOINTS]
    if len(usable) < 2:
        out["stopped"] = f"only {len(usable)} frame(s) have at least {MIN_KEYPOINTS} SIFT keypoints"
        return None
    t = phase("match")
    out["match"] = match(db, root, opts, len(names), swarm=len(cameras) > 1, own_pairs=not on_ray)
    if on_ray:
        out["match"]["ray"] = ray_info
    times["match"] = time.perf_counter() - t
    if out["match"]["verified_pairs"] == 0:
        out["stopped"] = "no pair of frames could be matched with a consistent geometry"
        return None
    return usable


def _settle(
    out: dict[str, Any],
    found: dict[str, dict[str, float]],
    root: Path,
    names: list[str],
    n_usable: int,
    opts: SfmOptions,
    refine_camera: bool,
    deadline: float | None,
    phase: Callable[..., float],
    on_register: Callable[[int], None],
) -> int:
    """Choose the model to keep among ``found`` into ``out["best"]``; extend it when frames
    are missing and re-register its pose jumps (both skipped once the time cap's ``deadline``
    passed). Returns the frames of the chosen model before the extension."""
    db, images, times = root / "database.db", root / "images", out["times"]
    best = _best(found)
    out["best"] = best
    out["init_pair"]["kept"] = Path(best).parent.name != ALT_MODELS  # our pair started it
    size = found[best]["frames"]
    if opts.extend and size < n_usable and not _out_of_time(deadline):
        opts = _capped(opts, deadline)
        t = phase("extend", size)
        ext = incremental_map(
            db, images, root / "extended", opts, refine_camera, on_register, input_path=Path(best)
        )
        times["extend"] = time.perf_counter() - t
        if ext:
            k = max(ext, key=lambda j: ext[j]["frames"])
            if ext[k]["frames"] > size:
                out["best"] = k
    jumps = jump_frames(Path(out["best"]), names)
    if jumps and not _out_of_time(deadline):  # fits its points, not the flight: again
        opts = _capped(opts, deadline)
        t = phase("re-register jumps", found[best]["frames"])
        out["best"], out["pose_jumps_remapped"] = remap_jumps(
            db, images, root, Path(out["best"]), jumps, names, opts, refine_camera, on_register
        )
        times["remap_jumps"] = time.perf_counter() - t
    return found[best]["frames"]


def _best(found: dict[str, dict[str, float]]) -> str:
    """The model of ``found`` with most frames; among equals, the lower reprojection error (the
    better basin)."""
    return max(found, key=lambda k: (found[k]["frames"], -found[k]["reproj"]))


def _capped(opts: SfmOptions, deadline: float | None) -> SfmOptions:
    """``opts`` with ``time_cap`` set to the seconds left until ``deadline`` (perf_counter)."""
    if deadline is None:
        return opts
    return dataclasses.replace(opts, time_cap=max(1.0, deadline - time.perf_counter()))


def _out_of_time(deadline: float | None) -> bool:
    """Whether a time cap is set and its ``deadline`` (perf_counter) has passed."""
    return deadline is not None and time.perf_counter() >= deadline


def bar_events(bar: Any, total: int) -> Callable[[tuple[Any, ...]], None]:
    """The handler of :func:`colmap_job`'s events for a progress ``bar`` (tqdm or
    :class:`dronecap.progress.LogProgress`): the phase as its description, the frames
    registered as its count and, while a phase registers frames, an ETA from that phase's own
    rate (the front end's minutes would otherwise make the bar's own estimate wrong)."""
    state = {"count": 0, "t0": time.monotonic(), "n0": 0}

    def on_event(ev: tuple[Any, ...]) -> None:
        if ev[0] == "phase":
            bar.set_description(f"sfm {ev[1]}")
            bar.update(ev[2] - state["count"])
            state.update(count=ev[2], t0=time.monotonic(), n0=ev[2])
        elif ev[0] == "registered":
            bar.update(ev[1])
            state["count"] += ev[1]
            done, dt = state["count"] - state["n0"], time.monotonic() - state["t0"]
            if done > 0 and dt > 0:
                left = max(total - state["count"], 0) * dt / done
                bar.set_postfix(registered=f"{state['count']}/{total}", eta=f"{left:.0f}s")

    return on_event


@dataclass
class ColmapResult:
    """What came back from COLMAP for one flight."""

    work: Path  # the work folder (database, images, models, log)
    names: list[str]  # work-folder name of each input frame, in flight order
    summary: dict[str, Any]  # colmap_job's summary
    reconstruction: Any = None  # pycolmap.Reconstruction of the chosen model, or None
    times: dict[str, float] = field(default_factory=dict)


def reconstruct(
    images: np.ndarray,
    work: Path,
    opts: SfmOptions,
    plan: CameraPlan,
    progress: bool = True,
    drones: np.ndarray | None = None,
) -> ColmapResult:
    """Run COLMAP on ``images`` (uint8 [N, H, W, C], flight order) inside ``work``; ``drones``
    (int [N]) gives every frame's drone for a swarm (a camera per drone, ``plan.cameras``).

    The frames are written gray (contrast-normalised first when ``opts.clahe``: the same
    :func:`dronecap.capture.contrast.normalize_contrast` ingest uses); ``plan`` is the camera.

    ``work`` is emptied first. Raises ChildCrash if COLMAP dies; every other failure to
    reconstruct is described in the returned summary's "stopped".
    """
    import cv2
    import pycolmap

    from dronecap.capture.contrast import normalize_contrast
    from dronecap.progress import progress_bar

    if work.exists():
        shutil.rmtree(work)
    (work / "images").mkdir(parents=True)
    names = image_names(np.zeros(len(images), np.int64) if drones is None else drones)
    for folder in {Path(n).parent for n in names}:
        (work / "images" / folder).mkdir(exist_ok=True)
    t = time.perf_counter()
    for name, im in zip(names, images, strict=True):
        gray = im[..., 0] if im.shape[-1] == 1 else cv2.cvtColor(im, cv2.COLOR_RGB2GRAY)
        if opts.clahe:
            gray = normalize_contrast(gray)
        cv2.imwrite(str(work / "images" / name), gray)
    times = {"write_images": time.perf_counter() - t}

    bar = progress_bar(total=len(names), desc="sfm", unit="frame", disable=not progress)

    on_event = bar_events(bar, len(names))

    job = {"work": str(work), "names": names, "options": opts.to_dict()}
    job.update(
        cameras=plan.colmap_per_drone(),
        refine_camera=plan.refine,
        refine_after=plan.refine_after,
    )
    try:
        summary = run_isolated(
            "dronecap.sfm.reconstruct:colmap_job",
            job,
            on_event,
            work / "colmap.log",
        )
    finally:
        bar.close()
    times.update(summary["times"])
    rec = None if summary["best"] is None else pycolmap.Reconstruction(summary["best"])
    return ColmapResult(work=work, names=names, summary=summary, reconstruction=rec, times=times)
