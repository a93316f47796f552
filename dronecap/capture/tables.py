"""The per-decoded-frame tables of an ingest as frames.h5 stores them under ``/extra``.

:func:`tables_to_extra` gives the stored arrays (scores, pair tables, defects, the selection
and, with telemetry, the pose priors); :func:`extra_to_tables` reads the tables back, so the
selection can be replayed without decoding (``dronecap ingest --replay``).
"""

from __future__ import annotations

import numpy as np

from dronecap.capture.quality import SCORE_NAMES
from dronecap.capture.selection import REASONS, Selection
from dronecap.capture.tracks import PAIR_NAMES
from dronecap.errors import InputError

# Per-decoded-frame tables as stored under /extra in frames.h5 (table name -> extra name).
EXTRA_NAMES = {name: name for name in (*SCORE_NAMES, *PAIR_NAMES)} | {
    "source_index": "decoded_source_index",
    "timestamp": "decoded_timestamp",
    "readable": "readable",
    "defect": "defect",
}
# Telemetry tables (present when the capture had telemetry), stored per decoded frame.
TELEMETRY_NAMES = {
    "prior_c2w": "decoded_prior_c2w",
    "prior_valid": "decoded_prior_valid",
    "frame_id": "decoded_frame_id",
    "camera_frame": "camera_frame",
    "dropped_before": "dropped_before",
}


def tables_to_extra(tables: dict[str, np.ndarray], sel: Selection) -> dict[str, np.ndarray]:
    """The arrays stored under ``/extra``: every table [N], ``keep`` uint8 [N], ``reason``
    int8 [N] and ``reason_legend`` str [len(REASONS)] (code -> name); with telemetry also the
    contract's per-KEPT-frame ``prior_c2w`` [M, 4, 4], ``prior_valid`` bool [M] and
    ``frame_id`` int64 [M]."""
    names = EXTRA_NAMES | TELEMETRY_NAMES
    extra = {names[k]: np.asarray(v) for k, v in tables.items() if k in names}
    extra["readable"] = extra["readable"].astype(np.uint8)
    extra["keep"] = sel.keep.astype(np.uint8)
    extra["reason"] = sel.reason.astype(np.int8)
    extra["reason_legend"] = np.array(REASONS)
    if "prior_c2w" in tables:
        kept = sel.keep
        extra["prior_c2w"] = np.asarray(tables["prior_c2w"], np.float64)[kept]
        extra["prior_valid"] = np.asarray(tables["prior_valid"], bool)[kept]
        extra["frame_id"] = np.asarray(tables["frame_id"], np.int64)[kept]
    return extra


def extra_to_tables(extra: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """Inverse of :func:`tables_to_extra` for the tables (what select_frames reads)."""
    missing = [v for v in EXTRA_NAMES.values() if v not in extra]
    if missing:
        raise InputError(
            f"has no ingest tables to replay (missing {', '.join(missing)}; "
            "files from before the feature-track selection need a new `dronecap ingest`)"
        )
    names = EXTRA_NAMES | {k: v for k, v in TELEMETRY_NAMES.items() if v in extra}
    return {k: np.asarray(extra[v]) for k, v in names.items()}
