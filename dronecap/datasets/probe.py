"""Reading a file without checksums in a forked child first, so that damage which crashes HDF5
(a segfault on corrupt metadata) or makes it loop forever is an error line, not a dead process.

Files that ``write_dataset`` writes (format_version 2) have the checksummed HDF5 1.10 superblock
and are read directly; everything else (version 1 files, foreign files) is probed: read once in
a child process, and only read in this process when the child survived. A probe costs one fork
and a second read of the file.
"""

from __future__ import annotations

import faulthandler
import os
import signal
from collections.abc import Callable
from pathlib import Path

HDF5_SIGNATURE = b"\x89HDF\r\n\x1a\n"
CHECKSUMMED_SUPERBLOCK = 3  # the superblock version of HDF5 1.10 files (what write_dataset makes)
PROBE_S = 10.0  # seconds a probe read may take, plus 1 s per 5 MB of file: longer is a hang


def checksummed_layout(path: Path) -> bool:
    """True when ``path`` starts with the HDF5 signature and the checksummed superblock (version
    3, byte 8); False for anything else, an unreadable file included."""
    try:
        with open(path, "rb") as f:
            head = f.read(9)
    except OSError:  # the caller's read says why
        return False
    return head[:8] == HDF5_SIGNATURE and head[8:] == bytes([CHECKSUMMED_SUPERBLOCK])


def survives_reading(
    path: Path, read: Callable[[Path], object], error: Callable[[str, Path], Exception]
) -> None:
    """Call ``read(path)`` in a forked child; raise ``error(message, path)`` when the child is
    killed by a signal (a crash inside HDF5) or still reading after :data:`PROBE_S` seconds
    (+1 s per 5 MB). An exception in the child is left for the caller's own read, which meets
    it again (same bytes, same code)."""
    limit = int(PROBE_S + path.stat().st_size / 5e6)
    # h5py itself takes its global lock around os.fork (an at-fork hook in h5py._objects), so
    # the child never inherits it held by another thread, which would make the child wait forever.
    pid = os.fork()
    if pid == 0:  # child: reports through its exit status only, never returns
        code = 1
        try:
            faulthandler.disable()  # a crash is reported by the parent, not as a traceback
            signal.signal(signal.SIGALRM, signal.SIG_DFL)  # a hang in HDF5 ends the child
            signal.alarm(limit)
            read(path)
            code = 0
        finally:
            os._exit(code)
    _, status = os.waitpid(pid, 0)
    if os.WIFSIGNALED(status):
        sig = os.WTERMSIG(status)
        what = (
            f"still reading after {limit} s"
            if sig == signal.SIGALRM
            else f"reading it crashed the HDF5 library ({signal.Signals(sig).name})"
        )
        raise error(f"damaged (no checksums to say where): {what}", path)
