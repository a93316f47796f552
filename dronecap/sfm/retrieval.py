"""Frames of other drones' flights that look alike: the pairs that can link a swarm's flights.

A bag of visual words built from the flights' own SIFT descriptors (no downloaded vocabulary):
k-means words from a sample of the descriptors, a tf-idf weighted word histogram per frame, and
the cosine similarity of the histograms. Every frame is paired with the
``per_frame`` most alike frames of the *other* drones' flights (its own flight is paired by the
sequential matcher). The cost is linear in frames apart from the [N, N] similarity product, which
is small next to matching (2000 frames: 4 M entries).

Why our own and not COLMAP's vocabulary-tree matcher: that one pairs each frame with its top
frames of *all* flights, mostly its own neighbours (already matched), so finding the cross-flight
pairs takes many retrieved frames per frame; on the 4-drone simulated corridor (282 frames, 20
per frame) it matched for 530 s on a loaded machine.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from dronecap.sfm.flights import flight_of

SAMPLE = 20000  # descriptors sampled to learn the words
WORDS = 256  # visual words (at most one per 40 sampled descriptors)
KMEANS_ITERATIONS = 15
CHUNK = 65536  # descriptors assigned to words per matrix product


def frame_histograms(descriptors: list[np.ndarray], seed: int = 0) -> np.ndarray:
    """tf-idf weighted, L2-normalised visual-word histograms, float32 [N, W], of frames given
    as SIFT descriptors (uint8 or float [K_i, 128] each; a frame with none gets a zero row)."""
    import cv2

    data = [np.asarray(d, np.float32) for d in descriptors]
    stacked = np.concatenate([d for d in data if len(d)] or [np.zeros((0, 128), np.float32)])
    if len(stacked) == 0:
        return np.zeros((len(data), 1), np.float32)
    rng = np.random.default_rng(seed)
    sample = stacked[rng.choice(len(stacked), min(SAMPLE, len(stacked)), replace=False)]
    words = int(max(2, min(WORDS, len(sample) // 40)))
    cv2.setRNGSeed(seed)
    criteria = (cv2.TERM_CRITERIA_MAX_ITER + cv2.TERM_CRITERIA_EPS, KMEANS_ITERATIONS, 1e-3)
    _, _, centres = cv2.kmeans(sample, words, None, criteria, 1, cv2.KMEANS_PP_CENTERS)
    hist = np.zeros((len(data), words), np.float32)
    for i, d in enumerate(data):
        if len(d):
            hist[i] = np.bincount(_nearest(d, centres), minlength=words)
    df = (hist > 0).sum(0)
    hist *= np.log(len(data) / np.maximum(df, 1)).astype(np.float32)  # idf: common words count less
    norm = np.linalg.norm(hist, axis=1, keepdims=True)
    return hist / np.maximum(norm, 1e-12)


def _nearest(x: np.ndarray, centres: np.ndarray) -> np.ndarray:
    """Index of the nearest of ``centres`` [W, D] for every row of ``x`` [K, D], int [K]."""
    c2 = (centres**2).sum(1)
    out = np.empty(len(x), np.int64)
    for a in range(0, len(x), CHUNK):
        block = x[a : a + CHUNK]
        out[a : a + CHUNK] = np.argmin(c2[None, :] - 2.0 * block @ centres.T, axis=1)
    return out


def cross_flight_pairs(hist: np.ndarray, flights: np.ndarray, per_frame: int) -> np.ndarray:
    """Pairs (i, j), i < j, int [P, 2]: every frame with its ``per_frame`` most alike frames of
    other flights (``hist``: [N, W] from :func:`frame_histograms`; ``flights``: int [N])."""
    sim = hist @ hist.T
    sim[flights[:, None] == flights[None, :]] = -np.inf  # never within a flight
    k = min(per_frame, int(np.max(np.sum(np.isfinite(sim), axis=1), initial=0)))
    if k == 0:
        return np.zeros((0, 2), np.int64)
    best = np.argpartition(-sim, k - 1, axis=1)[:, :k]  # [N, k]
    rows = np.repeat(np.arange(len(hist)), k)
    cols = best.ravel()
    ok = np.isfinite(sim[rows, cols])
    pairs = np.sort(np.stack([rows[ok], cols[ok]], 1), axis=1)
    return np.unique(pairs, axis=0)


def loop_pairs(
    hist: np.ndarray, flights: np.ndarray, period: int, per_query: int, min_gap: int
) -> np.ndarray:
    """Loop-closure pairs (i, j), i < j, int [P, 2], within each flight: every ``period``-th
    frame with its ``per_query`` most alike frames of its own flight at least ``min_gap``
    frames away (closer ones are the sequential matcher's). Frames in flight order; ``hist``
    from :func:`frame_histograms`. Cost: one [N/period, N] product."""
    n = len(hist)
    if n == 0:
        return np.zeros((0, 2), np.int64)
    queries = np.arange(0, n, period)
    sim = hist[queries] @ hist.T  # [Q, N]
    gap = np.abs(queries[:, None] - np.arange(n)[None, :])
    sim[(gap < min_gap) | (flights[queries, None] != flights[None, :])] = -np.inf
    k = min(per_query, n)
    best = np.argpartition(-sim, k - 1, axis=1)[:, :k]
    rows = np.repeat(queries, k)
    cols = best.ravel()
    ok = np.isfinite(sim[np.repeat(np.arange(len(queries)), k), cols])
    pairs = np.sort(np.stack([rows[ok], cols[ok]], 1), axis=1)
    return np.unique(pairs, axis=0)


def write_loop_pairs(
    database: Path, out_file: Path, period: int, per_query: int, min_gap: int, seed: int
) -> int:
    """Write COLMAP's pair list of :func:`loop_pairs` for the images in ``database``; returns
    the number of pairs."""
    names, flights, hist = _histograms_of(database, seed)
    pairs = loop_pairs(hist, flights, period, per_query, min_gap)
    out_file.write_text("".join(f"{names[a]} {names[b]}\n" for a, b in pairs))
    return len(pairs)


def _histograms_of(database: Path, seed: int) -> tuple[list[str], np.ndarray, np.ndarray]:
    """Image names in name (flight) order, their flights and word histograms."""
    import pycolmap

    with pycolmap.Database.open(database) as db:
        images = sorted(db.read_all_images(), key=lambda im: im.name)
        descs = [np.asarray(db.read_descriptors(im.image_id).data) for im in images]
    names = [im.name for im in images]
    flights = np.array([flight_of(n) for n in names], np.int64)
    return names, flights, frame_histograms(descs, seed)


def write_cross_flight_pairs(database: Path, out_file: Path, per_frame: int, seed: int) -> int:
    """Write COLMAP's pair list (``name1 name2`` lines) of the cross-flight pairs of the images
    in ``database`` (flights from their folders, :mod:`dronecap.sfm.flights`); returns the
    number of pairs."""
    names, flights, hist = _histograms_of(database, seed)
    pairs = cross_flight_pairs(hist, flights, per_frame)
    out_file.write_text("".join(f"{names[a]} {names[b]}\n" for a, b in pairs))
    return len(pairs)
