"""When the first attempt registers too little, try the report's remedies, within a time budget.

The remedies, in order (each only when it applies): exhaustive matching (instead of sequential),
contrast normalisation before SIFT (CLAHE, :mod:`dronecap.capture.contrast`), more features
(twice the keypoints, half the contrast threshold), finer SIFT scales (one more upsampling
octave, down to :data:`dronecap.sfm.options.FINEST_OCTAVE`; not offered when the first attempt
already went finer for sparse frames), and the known camera kept fixed (when ``--camera
estimate`` was asked although frames.h5 has a calibrated camera). Each attempt runs on top of
the best settings so far: a remedy that registered more frames stays, one that did not is
dropped. The loop stops as soon as ``opts.retry_below`` of the frames register, or when
``opts.retry_budget`` seconds have gone on retries (an attempt already started finishes). The
report's ``attempts`` lists every attempt (remedies in effect, frames registered, seconds)
and ``remedy`` names the one that produced the kept model.
"""

from __future__ import annotations

import dataclasses
import time
from pathlib import Path
from typing import Any

import numpy as np

from dronecap.sfm.camera_plan import CameraPlan
from dronecap.sfm.flights import flight_of
from dronecap.sfm.options import FINEST_OCTAVE, SfmOptions
from dronecap.sfm.reconstruct import ColmapResult, reconstruct

MAX_EXHAUSTIVE = 400  # frames: above this exhaustive matching is too slow to be a remedy


@dataclasses.dataclass
class Attempt:
    """One reconstruction attempt and what it gave."""

    remedies: list[str]  # remedies in effect (empty: the first attempt)
    result: ColmapResult
    seconds: float

    @property
    def registered(self) -> int:
        """Frames in the chosen model (0 when none)."""
        rec = self.result.reconstruction
        return 0 if rec is None else int(rec.num_reg_images())

    @property
    def linked_frames(self) -> int:
        """Frames of the flights linked into the model (a swarm's unlinked drones' frames
        cannot register in it), all frames for a single flight."""
        flights = self.result.summary.get("flights")
        if not flights:
            return len(self.result.names)
        return sum(flight_of(n) in flights["main"] for n in self.result.names)

    def to_dict(self) -> dict[str, Any]:
        """JSON-able summary for the report."""
        return {
            "remedies": self.remedies,
            "registered": self.registered,
            "seconds": round(self.seconds, 2),
            "work": self.result.work.name,
        }


def remedies(
    opts: SfmOptions, plan: CameraPlan, known: CameraPlan | None, n: int
) -> list[tuple[str, Any]]:
    """(name, change) pairs that apply, in order; a change maps (opts, plan) -> (opts, plan).

    ``known``: the fixed plan of a calibrated camera, when one exists and ``plan`` estimates.
    """
    out: list[tuple[str, Any]] = []
    if opts.resolved_matcher(n) == "sequential" and n <= MAX_EXHAUSTIVE:
        out.append(("exhaustive matching", lambda o, p: (_set(o, matcher="exhaustive"), p)))
    if not opts.clahe:
        out.append(("contrast normalisation (CLAHE)", lambda o, p: (_set(o, clahe=True), p)))
    out.append(
        (
            "more features",
            lambda o, p: (
                _set(
                    o,
                    max_features=2 * o.max_features,
                    peak_threshold=o.peak_threshold / 2,
                    finer_peak_threshold=o.finer_peak_threshold / 2,
                ),
                p,
            ),
        )
    )
    if opts.first_octave > FINEST_OCTAVE:
        finer = ("finer SIFT scales", lambda o, p: (_set(o, first_octave=o.first_octave - 1), p))
        out.append(finer)
    if known is not None and plan.mode == "estimate":
        out.append(("known camera, fixed", lambda o, p: (o, known)))
    return out


def _set(opts: SfmOptions, **changes: Any) -> SfmOptions:
    return dataclasses.replace(opts, **changes)


def reconstruct_with_retries(
    images: np.ndarray,
    sfm_dir: Path,
    opts: SfmOptions,
    plan: CameraPlan,
    known: CameraPlan | None,
    progress: bool = True,
    drones: np.ndarray | None = None,
) -> tuple[Attempt, list[Attempt]]:
    """The best attempt and all attempts (work folders ``work``, ``work_retry1``, ...);
    ``drones`` (int [N]): every frame's drone, for a swarm."""
    n = len(images)
    t = time.perf_counter()
    first = Attempt([], reconstruct(images, sfm_dir / "work", opts, plan, progress, drones), 0.0)
    first.seconds = time.perf_counter() - t
    attempts, best = [first], first
    # the octave SIFT ran at (finer than asked when the frames had few keypoints)
    octave = first.result.summary.get("first_octave", opts.first_octave)
    best_opts, best_plan = _set(opts, first_octave=octave), plan
    t_retry = time.perf_counter()
    for k, (name, change) in enumerate(remedies(best_opts, plan, known, n), start=1):
        if best.registered >= opts.retry_below * best.linked_frames:
            break
        if time.perf_counter() - t_retry > opts.retry_budget or opts.time_cap > 0:
            break  # a time-capped run keeps its model so far: no retries
        o, p = change(best_opts, best_plan)
        if progress:
            print(f"sfm: {best.registered}/{n} frames registered; retrying with {name}")
        t = time.perf_counter()
        res = reconstruct(images, sfm_dir / f"work_retry{k}", o, p, progress, drones)
        att = Attempt([*best.remedies, name], res, time.perf_counter() - t)
        attempts.append(att)
        if att.registered > best.registered:  # a remedy "worked" when more frames register
            best, best_opts, best_plan = att, o, p
    return best, attempts
