"""What an imported or shared file may make dronecap read, and how much of it.

- Image paths named by an imported file (a transforms.json ``file_path``, a COLMAP image name)
  stay inside the folder the file describes: ``../../x.png``, an absolute path or a symlink
  out of the folder is refused unless the user allows it (``--allow-outside``, which sets
  :data:`ALLOW_OUTSIDE` for the command). A FIFO, device or folder named as an image is refused
  (reading a FIFO blocks forever).
- A file's frame count is bounded (:data:`MAX_FRAMES`), and the memory the decoded images will
  take is estimated from the first image's header before anything is decoded: beyond what the
  process may allocate, one line naming ``--size``.
- An HDF5 file that links to other files (external links, virtual datasets, external raw
  storage) is refused: a dataset file is read alone.
"""

from __future__ import annotations

import contextlib
import os
import stat
from collections.abc import Iterator
from contextvars import ContextVar
from pathlib import Path

import h5py

from dronecap.errors import InputError
from dronecap.limits import check_memory, image_header_size

# True while a command runs with --allow-outside.
ALLOW_OUTSIDE: ContextVar[bool] = ContextVar("allow_outside", default=False)
MAX_FRAMES = 20_000  # frames one imported file may list (DRONECAP_MAX_FRAMES raises it)


@contextlib.contextmanager
def outside_allowed(allowed: bool) -> Iterator[None]:
    """Within the block, :func:`inside_folder` lets paths leave their folder when ``allowed``."""
    token = ALLOW_OUTSIDE.set(allowed)
    try:
        yield
    finally:
        ALLOW_OUTSIDE.reset(token)


def inside_folder(root: Path, path: Path, what: str = "file_path") -> Path:
    """``path`` (named by a file in folder ``root``) when it is a regular file (or missing: the
    reader reports that) inside ``root`` after following links; InputError otherwise."""
    if not ALLOW_OUTSIDE.get() and not path.resolve().is_relative_to(root.resolve()):
        raise InputError(
            f"{what} leaves the folder {root} (a '..', absolute path or link out of it): "
            "refused; pass --allow-outside if you trust this file",
            path,
        )
    try:
        mode = path.stat().st_mode
    except OSError:
        return path
    if not stat.S_ISREG(mode):
        raise InputError(f"{what} is not a regular file (a FIFO, device or folder)", path)
    return path


def check_frame_count(n: int, path: Path) -> None:
    """Refuse a file listing more than :data:`MAX_FRAMES` frames (or the value of the
    ``DRONECAP_MAX_FRAMES`` environment variable)."""
    limit = int(os.environ.get("DRONECAP_MAX_FRAMES", MAX_FRAMES))
    if n > limit:
        raise InputError(
            f"lists {n} frames, more than the limit of {limit} (set DRONECAP_MAX_FRAMES to "
            "raise it)",
            path,
        )


def check_import_memory(paths: list[Path], width: int, source: Path) -> None:
    """Estimate the memory of importing ``paths`` at ``width`` pixels (RGBA while decoding one
    full image, then RGB + alpha of every stored image) from the first image's header."""
    if not paths:
        return
    w0, h0 = image_header_size(paths[0])
    h = max(1, round(width * h0 / max(w0, 1)))
    stored = len(paths) * width * h * 4
    check_memory(w0 * h0 * 4 * 2 + stored, f"{len(paths)} images", "lower --size", source)


def hdf5_link_problem(f: h5py.File) -> str | None:
    """What makes HDF5 file ``f`` reach outside itself (an external link, a virtual dataset or
    a dataset stored in external raw files), or None; walked without following any link."""

    def walk(group: h5py.Group, prefix: str) -> str | None:
        for name in group:
            where = f"{prefix}{name}"
            link = group.get(name, getlink=True)
            if isinstance(link, h5py.ExternalLink):
                return f"{where}: an external link to {link.filename}: refused"
            if isinstance(link, h5py.SoftLink):
                continue
            obj = group[name]
            if isinstance(obj, h5py.Group) and (found := walk(obj, f"{where}/")):
                return found
            if isinstance(obj, h5py.Dataset) and (obj.is_virtual or obj.external):
                return f"{where}: data stored in other files (virtual or external): refused"
        return None

    return walk(f, "")
