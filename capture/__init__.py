"""dronecap.capture: flight video -> 160x160 gray selected frames, and a flight simulator.

- :func:`ingest` decodes a video or image folder, converts every frame (BT.601 gray, centre crop,
  area resize), scores it and selects frames; :func:`select_frames` replays the selection from
  stored score tables.
- :func:`simulate` renders a nano-drone flight (corridor or orbit) to a video plus ground truth.

Heavy libraries (OpenCV, open3d, tqdm) are imported inside the functions that use them.
"""

from dronecap.capture.ingest import (
    IngestParams,
    IngestResult,
    extra_to_tables,
    ingest,
    tables_to_extra,
)
from dronecap.capture.selection import REASONS, Selection, SelectionParams, select_frames
from dronecap.capture.simulate import render_flight, simulate

__all__ = [
    "REASONS",
    "IngestParams",
    "IngestResult",
    "Selection",
    "SelectionParams",
    "extra_to_tables",
    "ingest",
    "render_flight",
    "select_frames",
    "simulate",
    "tables_to_extra",
]
