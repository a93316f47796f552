"""dronecap.capture: flight video or drone capture folder -> 160x160 gray selected frames.

- :func:`ingest` decodes a video or image folder (NanoCockpit / PULP-Dronet captures with their
  telemetry: :mod:`.telemetry`), demosaics raw Bayer frames and finds torn and upside-down ones
  (:mod:`.defects`), converts every frame (BT.601 gray, centre crop, area resize), scores it
  (:mod:`.quality`), tracks features through it (:mod:`.tracks`) and selects frames;
  :func:`select_frames` replays the selection from the stored tables.

Heavy libraries (OpenCV, open3d) are imported inside the functions that use them.
"""

from dronecap.capture.ingest import IngestParams, IngestResult, ingest
from dronecap.capture.selection import REASONS, Selection, SelectionParams, select_frames
from dronecap.capture.tables import extra_to_tables, tables_to_extra

__all__ = [
    "REASONS",
    "IngestParams",
    "IngestResult",
    "Selection",
    "SelectionParams",
    "extra_to_tables",
    "ingest",
    "select_frames",
    "tables_to_extra",
]
