"""TUM trajectory files: one pose per line, ``timestamp tx ty tz qx qy qz qw``.

The format of the TUM RGB-D benchmark (and of evo, ORB-SLAM, ...): the timestamp in seconds,
the camera centre in world units and the camera-to-world rotation as a unit quaternion (Hamilton
convention, scalar last). Lines starting with ``#`` and blank lines are comments. dronecap reads
and writes camera-to-world 4x4 matrices in OpenCV camera axes (x right, y down, z forward); TUM
files do not say which camera axes they use, so the caller's convention passes through unchanged.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from dronecap.errors import InputError
from dronecap.files import atomic_output


def read_tum(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """Read a TUM trajectory.

    Returns:
        timestamps float64 [N] (seconds, as in the file), c2w float64 [N, 4, 4].

    Raises:
        InputError: a missing file, a line without 8 numbers, a non-finite value, a quaternion
            far from unit length (|q| outside [0.9, 1.1]), or no pose at all.
    """
    from scipy.spatial.transform import Rotation

    path = Path(path)
    try:
        lines = path.read_text().splitlines()
    except (OSError, UnicodeDecodeError) as err:
        raise InputError(f"cannot read trajectory: {err}", path) from None
    rows = []
    for no, line in enumerate(lines, 1):
        text = line.strip()
        if not text or text.startswith("#"):
            continue
        parts = text.replace(",", " ").split()
        try:
            vals = [float(x) for x in parts]
        except ValueError:
            vals = []
        if len(vals) != 8 or not np.isfinite(vals).all():
            raise InputError(
                f"line {no}: expected 8 finite numbers 'timestamp tx ty tz qx qy qz qw', "
                f"found {text[:60]!r}",
                path,
            )
        norm = float(np.linalg.norm(vals[4:]))
        if not 0.9 <= norm <= 1.1:
            raise InputError(f"line {no}: quaternion length {norm:.3g} is not 1", path)
        rows.append(vals)
    if not rows:
        raise InputError("no poses in the trajectory file", path)
    a = np.array(rows)
    c2w = np.tile(np.eye(4), (len(a), 1, 1))
    c2w[:, :3, :3] = Rotation.from_quat(a[:, 4:8]).as_matrix()  # normalises the quaternion
    c2w[:, :3, 3] = a[:, 1:4]
    return a[:, 0].copy(), c2w


def write_tum(path: str | Path, timestamps: np.ndarray, c2w: np.ndarray) -> Path:
    """Write poses as a TUM trajectory (atomically).

    Args:
        timestamps: float [N] seconds.
        c2w: float [N, 4, 4] camera-to-world with orthonormal rotations.

    Raises:
        ValueError: mismatched lengths or non-finite values.
    """
    from scipy.spatial.transform import Rotation

    t = np.asarray(timestamps, np.float64).reshape(-1)
    m = np.asarray(c2w, np.float64)
    if m.shape != (len(t), 4, 4) or not (np.isfinite(t).all() and np.isfinite(m).all()):
        raise ValueError(f"need N timestamps and N finite 4x4 poses, got {t.shape} and {m.shape}")
    q = Rotation.from_matrix(m[:, :3, :3]).as_quat()  # x, y, z, w
    rows = np.column_stack([t, m[:, :3, 3], q])
    path = Path(path)
    with atomic_output(path) as tmp, open(tmp, "w") as f:
        f.write("# timestamp tx ty tz qx qy qz qw (camera-to-world)\n")
        np.savetxt(f, rows, fmt="%.9f")
    return path
