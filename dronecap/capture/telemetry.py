"""Drone capture folders: their telemetry CSV, matched to the frames, and camera pose priors.

Layouts (the telemetry contract; ``dronecap simulate --format ...`` writes the first two):

========== ============================ ============================================= =========
layout     files                        columns read (canonical name <- CSV column)    units
========== ============================ ============================================= =========
nanocockpit camera_raw/NNNNN.png,       file <- filename, frame_id, time <-            mm, us
           metadata.csv (a row per      frame_timestamp, x y z, qx qy qz qw
           received frame)
pulp-dronet images/<ticks>.jpeg,        time <- timeTicks, x <- stateEstimate.x, ...,  m, us
           state.csv (~100 Hz)          qx <- stateEstimate.qx, ...; frame time =
                                        the file name (us); nearest row within 20 ms
bitcraze   images + a CSV               file <- image_name, time <- timestamp,         m, ms
                                        x y z, qw qx qy qz
========== ============================ ============================================= =========

Other CSVs: ``--telemetry FILE --columns file=img,time=t_us,x=px,...`` maps canonical names
(``file frame_id time x y z qx qy qz qw``) to the file's columns; ``unit=mm|m`` and
``time_unit=us|ms|s`` give the units (default m and us). With a ``file`` column, rows are
matched to frames by file name; without one, frames are matched to the nearest row in time
(frame time from a numeric file name, in the time unit).

The pose is the drone BODY (x forward, y left, z up) in a z-up world, quaternion body-to-world
(Hamilton, scalar last). The camera looks along body +x: ``c2w = [R_wb @ BODY_FROM_CAMERA,
p + R_wb @ offset]`` in OpenCV camera axes and metres.

Dropped frames: the 8-bit hardware ``frame_id`` counts every captured frame (wrapping 255 ->
0), so a jump of more than one is a gap; the frame times resolve jumps of 256 or more. Without
frame ids, gaps in the frame times (a multiple of the median frame period) are used.
"""

from __future__ import annotations

import csv
import math
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from dronecap.errors import InputError

# camera axes in body coordinates (columns): cam_x = -body_y, cam_y = -body_z, cam_z = body_x
BODY_FROM_CAMERA = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
MAX_MATCH_US = 20_000  # a frame farther than this from every state row has no prior
ID_MODULO = 256  # the hardware frame counter is 8 bit
CANONICAL = ("file", "frame_id", "time", "x", "y", "z", "qx", "qy", "qz", "qw")
POSE = ("x", "y", "z", "qx", "qy", "qz", "qw")
TIME_UNITS = {"us": 1e-6, "ms": 1e-3, "s": 1.0}
POSITION_UNITS = {"mm": 1e-3, "m": 1.0}


@dataclass(frozen=True)
class Layout:
    """A telemetry CSV layout: canonical name -> CSV column, and the units."""

    name: str
    columns: dict[str, str]
    unit: str = "m"  # positions
    time_unit: str = "us"
    image_dir: str | None = None  # frames sub-folder of the capture folder
    csv_name: str | None = None  # telemetry file name in the capture folder


PULP = {k: f"stateEstimate.{k}" for k in POSE}
LAYOUTS = (
    Layout(
        "nanocockpit",
        {"file": "filename", "frame_id": "frame_id", "time": "frame_timestamp"}
        | {k: k for k in POSE},
        unit="mm",
        image_dir="camera_raw",
        csv_name="metadata.csv",
    ),
    Layout("pulp-dronet", {"time": "timeTicks"} | PULP, image_dir="images", csv_name="state.csv"),
    Layout(
        "bitcraze",
        {"file": "image_name", "time": "timestamp"} | {k: k for k in POSE},
        time_unit="ms",
    ),
)


@dataclass
class Telemetry:
    """Telemetry matched to N decoded frames (arrays [N])."""

    layout: str
    path: Path
    prior_c2w: np.ndarray  # float64 [N, 4, 4] camera-to-world, OpenCV axes, metres, z up
    prior_valid: np.ndarray  # bool [N]
    frame_id: np.ndarray  # int64 [N], -1 where unknown
    camera_frame: np.ndarray  # int64 [N] camera frame number (first frame = its id), -1 unknown
    frame_time: np.ndarray  # float64 [N] capture time in seconds from the first frame, NaN unknown
    dropped: list[int] = field(default_factory=list)  # camera frame numbers never delivered

    @property
    def dropped_before(self) -> np.ndarray:
        """int64 [N]: frames lost just before each delivered frame (0 for the first)."""
        out = np.zeros(len(self.camera_frame), np.int64)
        out[1:] = np.maximum(np.diff(self.camera_frame) - 1, 0)
        out[1:][self.camera_frame[1:] < 0] = 0
        return out

    def record(self) -> dict[str, object]:
        """The ``telemetry`` stage attribute (contract)."""
        return {
            "format": self.layout,
            "file": str(self.path),
            "matched": int(self.prior_valid.sum()),
            "dropped_frames": [int(d) for d in self.dropped],
        }


def parse_columns(text: str | None) -> dict[str, str]:
    """``--columns file=img,time=t,unit=mm`` -> dict; ValueError naming the bad entry."""
    out: dict[str, str] = {}
    for item in filter(None, (text or "").split(",")):
        key, sep, value = item.partition("=")
        key, value = key.strip(), value.strip()
        if not sep or not value or key not in (*CANONICAL, "unit", "time_unit"):
            raise ValueError(
                f"--columns: {item!r} is not NAME=COLUMN with NAME one of "
                f"{', '.join(CANONICAL)}, unit, time_unit"
            )
        out[key] = value
    if out.get("unit", "m") not in POSITION_UNITS:
        raise ValueError(f"--columns: unit must be mm or m, got {out['unit']!r}")
    if out.get("time_unit", "us") not in TIME_UNITS:
        raise ValueError(f"--columns: time_unit must be us, ms or s, got {out['time_unit']!r}")
    return out


def find_capture(folder: Path) -> tuple[Path, Path | None, Layout | None]:
    """(frames folder, telemetry CSV or None, its layout) of a capture folder."""
    for lay in LAYOUTS:
        if lay.image_dir and lay.csv_name and (folder / lay.image_dir).is_dir():
            csv_path = folder / lay.csv_name
            return folder / lay.image_dir, csv_path if csv_path.is_file() else None, lay
    csvs = sorted(folder.glob("*.csv"))
    for c in csvs:
        header = _header(c)
        for lay in LAYOUTS:
            if set(lay.columns.values()) <= set(header):
                return folder, c, lay
    return folder, None, None


def _header(path: Path) -> list[str]:
    try:
        with open(path, newline="", encoding="utf-8-sig") as fh:
            return [h.strip() for h in next(csv.reader(fh), [])]
    except (OSError, UnicodeDecodeError, csv.Error):
        return []


def layout_for(path: Path, columns: dict[str, str], guess: Layout | None) -> Layout:
    """The layout of telemetry file ``path``: ``columns`` (from ``--columns``) override the
    guessed or header-detected one."""
    header = set(_header(path))
    base = guess
    if base is None:
        base = next((lay for lay in LAYOUTS if set(lay.columns.values()) <= header), None)
    if base is None and not columns:
        known = "; ".join(f"{lay.name}: {', '.join(lay.columns.values())}" for lay in LAYOUTS)
        raise InputError(f"unknown telemetry columns (known layouts: {known}; or --columns)", path)
    mapping = dict(base.columns) if base else {}
    mapping.update({k: v for k, v in columns.items() if k in CANONICAL})
    return Layout(
        base.name if base and not columns else "custom",
        mapping,
        unit=columns.get("unit", base.unit if base else "m"),
        time_unit=columns.get("time_unit", base.time_unit if base else "us"),
    )


def read_table(path: Path, layout: Layout) -> tuple[dict[str, np.ndarray], np.ndarray]:
    """The mapped columns of a telemetry CSV and the file line of each row.

    Returns:
        ({canonical name: array [R]} with ``file`` as str and the rest float64, lines int [R]).

    Raises:
        InputError: missing columns, a non-numeric or non-finite value, a time going backwards,
            or a quaternion far from unit length; the message names the line.
    """
    try:
        fh = open(path, newline="", encoding="utf-8-sig")
    except OSError as err:
        raise InputError(f"cannot read telemetry ({err.strerror})", path) from None
    try:
        with fh:
            reader = csv.reader(fh)
            header = [h.strip() for h in next(reader, [])]
            values, lines = _parse_rows(reader, header, layout, path)
    except (UnicodeDecodeError, csv.Error) as err:
        raise InputError(f"is not a readable CSV text file ({err})", path) from None
    if not lines:
        raise InputError("telemetry has a header but no rows", path)
    table = {k: np.asarray(v, dtype=object if k == "file" else float) for k, v in values.items()}
    line_of = np.asarray(lines)
    if "time" in table:
        back = np.flatnonzero(np.diff(table["time"]) < 0)
        if len(back):
            r = int(back[0]) + 1
            raise InputError(
                f"line {line_of[r]}: {layout.columns['time']} goes backwards "
                f"({table['time'][r]:.0f} after {table['time'][r - 1]:.0f})",
                path,
            )
    if all(k in table for k in ("qx", "qy", "qz", "qw")):
        norm = np.linalg.norm(np.stack([table[k] for k in ("qx", "qy", "qz", "qw")], 1), axis=1)
        bad = np.flatnonzero(np.abs(norm - 1.0) > 0.05)
        if len(bad):
            r = int(bad[0])
            raise InputError(f"line {line_of[r]}: quaternion has norm {norm[r]:.3f}, not 1", path)
    return table, line_of


def _parse_rows(
    reader: Iterator[list[str]], header: list[str], layout: Layout, path: Path
) -> tuple[dict[str, list[object]], list[int]]:
    """The mapped columns of the rows after the header, and each row's file line."""
    missing = [c for c in layout.columns.values() if c not in header]
    if missing:
        raise InputError(
            f"telemetry ({layout.name}) lacks column(s) {', '.join(missing)}; "
            f"it has {', '.join(header) or 'no header'}",
            path,
        )
    at = {k: header.index(c) for k, c in layout.columns.items()}
    values: dict[str, list[object]] = {k: [] for k in at}
    lines: list[int] = []
    for line, row in enumerate(reader, start=2):
        if not any(cell.strip() for cell in row):
            continue
        if len(row) < len(header):
            raise InputError(f"line {line}: {len(row)} values, header has {len(header)}", path)
        for k, i in at.items():
            cell = row[i].strip()
            if k == "file":
                values[k].append(cell)
                continue
            try:
                v = float(cell)
            except ValueError:
                v = math.nan
            if not math.isfinite(v):
                msg = f"line {line}: {layout.columns[k]} = {cell!r} is not a finite number"
                raise InputError(msg, path)
            values[k].append(v)
        lines.append(line)
    return values, lines


def camera_poses(
    position: np.ndarray, quat_xyzw: np.ndarray, offset: np.ndarray | None = None
) -> np.ndarray:
    """c2w float64 [R, 4, 4] (OpenCV camera axes) of body positions [R, 3] (metres) and
    body-to-world quaternions [R, 4] (x, y, z, w); ``offset`` [3]: camera in body axes (m)."""
    from scipy.spatial.transform import Rotation

    r_wb = Rotation.from_quat(quat_xyzw).as_matrix()
    out = np.tile(np.eye(4), (len(position), 1, 1))
    out[:, :3, :3] = r_wb @ BODY_FROM_CAMERA
    out[:, :3, 3] = position + (r_wb @ offset if offset is not None else 0.0)
    return out


def unwrap_frame_ids(ids: np.ndarray, times: np.ndarray | None) -> np.ndarray:
    """Camera frame numbers [N] of delivered 8-bit frame ids [N] (first = its id).

    A jump of ``(id_k - id_{k-1}) mod 256`` frames is ambiguous by multiples of 256; with frame
    times [N] (any unit) the multiple closest to the elapsed time / the median frame period is
    taken.
    """
    ids = np.asarray(ids, np.int64)
    step = np.mod(np.diff(ids), ID_MODULO)
    if times is not None and len(ids) > 2:
        dt = np.diff(np.asarray(times, float))
        single = dt[step == 1]
        period = (
            float(np.median(single)) if len(single) else float(np.median(dt / np.maximum(step, 1)))
        )
        if period > 0:
            laps = np.rint((dt / period - step) / ID_MODULO)
            step = step + ID_MODULO * np.maximum(laps, 0).astype(np.int64)
    return ids[0] + np.r_[0, np.cumsum(step)]


def frames_from_times(times: np.ndarray) -> np.ndarray:
    """Camera frame numbers [N] (first = 0) of frame times [N]: multiples of the median period."""
    dt = np.diff(np.asarray(times, float))
    if len(dt) == 0:
        return np.zeros(len(times), np.int64)
    period = float(np.median(dt))
    if period <= 0:
        return np.arange(len(times), dtype=np.int64)
    return np.r_[0, np.cumsum(np.maximum(np.rint(dt / period), 1))].astype(np.int64)


def match(
    path: Path,
    layout: Layout,
    names: list[str],
    offset: np.ndarray | None = None,
) -> Telemetry:
    """Match N decoded frames (file names relative to the frames folder) to telemetry ``path``."""
    table, _ = read_table(path, layout)
    n = len(names)
    to_m = POSITION_UNITS[layout.unit]
    to_s = TIME_UNITS[layout.time_unit]
    pose_ok = all(k in table for k in POSE)
    c2w_rows = (
        camera_poses(
            np.stack([table[k] for k in "xyz"], 1) * to_m,
            np.stack([table[k] for k in ("qx", "qy", "qz", "qw")], 1),
            offset,
        )
        if pose_ok
        else None
    )
    row = np.full(n, -1, np.int64)
    frame_time = np.full(n, np.nan)
    if "file" in table:
        index = {Path(str(f)).name: i for i, f in enumerate(table["file"])}
        for k, name in enumerate(names):
            row[k] = index.get(Path(name).name, -1)
        if "time" in table:
            frame_time[row >= 0] = table["time"][row[row >= 0]] * to_s
    else:
        stamps = np.array([_number(Path(nm).stem) for nm in names])
        if "time" not in table or np.isnan(stamps).any():
            raise InputError(
                "telemetry has no file column, so frames are matched by time: frame files must "
                "be named by their capture time (e.g. images/1234567.jpeg)",
                path,
            )
        near = _nearest(table["time"], stamps)
        close = np.abs(table["time"][near] - stamps) * to_s <= MAX_MATCH_US * 1e-6
        row[close] = near[close]
        frame_time = stamps * to_s
    valid = (row >= 0) & pose_ok
    c2w = np.tile(np.eye(4), (n, 1, 1))
    if c2w_rows is not None:
        c2w[valid] = c2w_rows[row[valid]]
    frame_id = np.full(n, -1, np.int64)
    if "frame_id" in table:
        frame_id[row >= 0] = table["frame_id"][row[row >= 0]].astype(np.int64)
    camera_frame = np.full(n, -1, np.int64)
    if (frame_id >= 0).all() and n:
        times = frame_time if np.isfinite(frame_time).all() else None
        camera_frame = unwrap_frame_ids(frame_id, times)
    elif np.isfinite(frame_time).all() and n:
        camera_frame = frames_from_times(frame_time)
    if np.isfinite(frame_time).any():
        frame_time = frame_time - np.nanmin(frame_time)
    dropped: list[int] = []
    if (camera_frame >= 0).all() and n:
        have = set(camera_frame.tolist())
        dropped = [f for f in range(int(camera_frame[0]), int(camera_frame[-1])) if f not in have]
    return Telemetry(layout.name, path, c2w, valid, frame_id, camera_frame, frame_time, dropped)


def _nearest(t: np.ndarray, x: np.ndarray) -> np.ndarray:
    """Index of the value of sorted ``t`` [R] nearest to each of ``x`` [N]."""
    hi = np.clip(np.searchsorted(t, x), 0, len(t) - 1)
    lo = np.maximum(hi - 1, 0)
    return np.where(np.abs(t[lo] - x) <= np.abs(t[hi] - x), lo, hi)


def _number(text: str) -> float:
    try:
        return float(text)
    except ValueError:
        return math.nan
