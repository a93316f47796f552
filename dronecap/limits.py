"""How much a file may make dronecap decode or allocate: the limits every reader shares.

An image's size is read from its header before any pixel is decoded (a decompression bomb is
refused in one line), and an allocation is compared with the memory this process may still use
(the machine's available memory and the ``ulimit -v`` address-space limit) before it is made.
A shared base: it imports no stage.
"""

from __future__ import annotations

import contextlib
import os
import resource
from pathlib import Path

import numpy as np

from dronecap.errors import InputError

# Largest image or video frame decoded, in pixels (DRONECAP_MAX_PIXELS raises it): 64 MP, far
# above any drone camera, far below a decompression bomb (30000x30000 = 900 MP, 3.6 GB decoded).
MAX_PIXELS = 64_000_000
MEMORY_SHARE = 0.7  # of the memory this process may still allocate, for the decoded images


def available_bytes() -> int:
    """Bytes this process may still allocate: the smaller of the machine's available memory and
    what the address-space limit (``ulimit -v``) leaves."""
    free = 1 << 62
    with contextlib.suppress(OSError, ValueError, IndexError):
        for line in Path("/proc/meminfo").read_text().splitlines():
            if line.startswith("MemAvailable:"):
                free = int(line.split()[1]) * 1024
    soft, _ = resource.getrlimit(resource.RLIMIT_AS)
    if soft != resource.RLIM_INFINITY:
        used = 0
        with contextlib.suppress(OSError, ValueError, IndexError):
            for line in Path("/proc/self/status").read_text().splitlines():
                if line.startswith("VmSize:"):
                    used = int(line.split()[1]) * 1024
        free = min(free, soft - used)
    return max(free, 0)


def check_memory(nbytes: int, what: str, option: str, path: Path | str | None = None) -> None:
    """Refuse before allocating ``nbytes`` for ``what`` when it exceeds :data:`MEMORY_SHARE`
    of :func:`available_bytes`; the line names the ``option`` that lowers it."""
    budget = int(available_bytes() * MEMORY_SHARE)
    if nbytes > budget:
        raise InputError(
            f"{what} would need about {nbytes / 1e9:.1f} GB, more than the {budget / 1e9:.1f} GB "
            f"this process can use: {option}",
            path,
        )


def image_header_size(path: Path) -> tuple[int, int]:
    """(width, height) of an image file read from its header only (PIL's lazy open: no pixel
    is decoded). InputError when it is not an image PIL can identify."""
    from PIL import Image, UnidentifiedImageError

    limit, Image.MAX_IMAGE_PIXELS = Image.MAX_IMAGE_PIXELS, None  # check_frame_pixels decides
    try:
        with Image.open(path) as im:  # the header only
            return int(im.width), int(im.height)
    except (OSError, UnidentifiedImageError, ValueError, SyntaxError) as err:
        raise InputError(f"not a readable image: {err}", path) from None
    finally:
        Image.MAX_IMAGE_PIXELS = limit


def check_frame_pixels(width: int, height: int, path: Path) -> None:
    """Refuse to decode a ``width`` x ``height`` frame beyond :data:`MAX_PIXELS` (or
    ``DRONECAP_MAX_PIXELS``), or one whose decoded copy would not fit in memory."""
    limit = int(os.environ.get("DRONECAP_MAX_PIXELS", MAX_PIXELS))
    if width * height > limit:
        raise InputError(
            f"is {width}x{height} ({width * height / 1e6:.0f} MP), more than the "
            f"{limit / 1e6:.0f} MP a frame may have (set DRONECAP_MAX_PIXELS to raise it)",
            path,
        )
    check_memory(width * height * 4 * 4, "decoding this frame", "free some memory", path)


def read_image(path: Path) -> np.ndarray | None:
    """cv2.imread of ``path`` (uint8/uint16 [H, W(, C)], None when it does not decode) after
    checking its header's size with :func:`check_frame_pixels`."""
    import cv2

    try:
        w, h = image_header_size(path)
    except InputError:
        return None  # no readable header: reported as an image that does not decode
    check_frame_pixels(w, h, path)
    return cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
