"""Small file helpers shared by every stage: atomic writes, free-space checks, content hashes.

Writers go through :func:`atomic_output`: the output appears under its final name only when it
is complete, the temporary file is removed on every path (error, Ctrl-C, full disk), and a
failure of the storage itself (full disk, read-only filesystem, a folder where a file should go,
no permission) becomes an :class:`~dronecap.errors.OutputError`: one line naming the output.
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import glob
import hashlib
import os
import re
import shutil
import sys
import tempfile
import time
from collections.abc import Callable, Iterator
from pathlib import Path

from dronecap.errors import OutputError

# errno values that mean "this output cannot be written here", not a bug
STORAGE_ERRNOS = {
    errno.ENOSPC: "no space left on the device",
    errno.EDQUOT: "disk quota exceeded",
    errno.EFBIG: "file too large for the filesystem",
    errno.EROFS: "read-only filesystem",
    errno.EACCES: "permission denied",
    errno.EPERM: "operation not permitted",
    errno.EISDIR: "is a folder, expected a file",
    errno.ENOTDIR: "a parent of the path is a file, not a folder",
    errno.EEXIST: "a file is in the way of a folder",
    errno.ENOTEMPTY: "is a folder that is not empty",
    errno.ENAMETOOLONG: "file name too long",
}


def storage_error(err: BaseException) -> str | None:
    """What ``err`` says about the storage (one of :data:`STORAGE_ERRNOS`), or None when it is
    some other error. Understands h5py's OSErrors, which carry the errno only in their text."""
    if not isinstance(err, OSError):
        return None
    code = err.errno
    if code is None:
        m = re.search(r"errno = (\d+)", str(err))
        code = int(m.group(1)) if m else None
        if code is None and "No space left" in str(err):
            code = errno.ENOSPC
    return STORAGE_ERRNOS.get(code) if code is not None else None


WAIT_ENV = "DRONECAP_WAIT"  # "1": a second writer of an output waits instead of stopping
_HELD: set[Path] = set()  # lock files this process holds (a nested lock of one is a no-op)


def lock_path(path: str | Path) -> Path:
    """The lock file of output ``path``: named by the hash of its resolved absolute path, in
    this user's lock folder (so taking a lock never writes into the user's folders, which may
    not exist yet, be read-only or full)."""
    key = hashlib.sha256(str(Path(path).resolve()).encode()).hexdigest()[:32]
    runtime = os.environ.get("XDG_RUNTIME_DIR") or tempfile.gettempdir()
    return Path(runtime) / f"dronecap-locks-{os.getuid()}" / f"{key}.lock"


@contextlib.contextmanager
def output_lock(path: str | Path, wait: bool | None = None) -> Iterator[None]:
    """Hold the lock of output ``path`` (a file or a folder) for the block: an exclusive
    ``flock`` on its :func:`lock_path`, which is removed again on release.

    A second process writing the same output stops with one line (OutputError), or with
    ``wait`` (default: the ``DRONECAP_WAIT`` environment variable, set by ``dronecap --wait``)
    says once that it waits and waits. Re-entrant within a process. The lock dies with its
    process, so a killed writer never leaves a lock held.
    """
    lock = lock_path(path)
    if lock in _HELD:
        yield
        return
    if wait is None:
        wait = os.environ.get(WAIT_ENV) == "1"
    lock.parent.mkdir(mode=0o700, parents=True, exist_ok=True)
    fd = _acquire(lock, Path(path), wait)
    _HELD.add(lock)
    try:
        yield
    finally:
        _HELD.discard(lock)
        with contextlib.suppress(OSError):
            os.unlink(lock)  # still held: a waiter re-checks that its file is the current one
        os.close(fd)


def _acquire(lock: Path, shown: Path, wait: bool) -> int:
    """An fd holding the flock of ``lock`` (the file currently at that path)."""
    told = False
    while True:
        fd = os.open(lock, os.O_RDWR | os.O_CREAT, 0o644)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = os.pread(fd, 64, 0).decode(errors="replace").strip() or "?"
            if not wait:
                os.close(fd)
                raise OutputError(
                    f"is being written by another dronecap command (pid {holder}): not writing "
                    "it twice at once; run again when it ends (dronecap --wait waits)",
                    shown,
                ) from None
            if not told:
                print(f"dronecap: waiting for pid {holder}, which is writing {shown}",
                      file=sys.stderr, flush=True)  # fmt: skip
                told = True
            fcntl.flock(fd, fcntl.LOCK_EX)
        try:
            same = os.fstat(fd).st_ino == os.stat(lock).st_ino
        except FileNotFoundError:
            same = False
        if same:  # not a file its previous holder removed meanwhile
            os.ftruncate(fd, 0)
            os.pwrite(fd, str(os.getpid()).encode(), 0)
            return fd
        os.close(fd)
        time.sleep(0.01)


# What an output's name says it holds (its conventional name's suffix), and how to recognise it.
FILE_KINDS = {".h5": "an HDF5 file", ".json": "a JSON file", ".png": "a PNG image"}
FILE_KINDS |= dict.fromkeys((".mp4", ".mov", ".avi", ".mkv"), "a video")


OUTPUT_SETTINGS = ("output", "out")  # the settings that name a command's output


def file_kind(path: Path) -> str | None:
    """Which of :data:`FILE_KINDS` the bytes of ``path`` are (None: none of them)."""
    with open(path, "rb") as fh:
        head = fh.read(16)
    if head.startswith(b"\x89HDF\r\n\x1a\n"):
        return "an HDF5 file"
    if head.startswith(b"\x89PNG"):
        return "a PNG image"
    if head[4:8] == b"ftyp" or head.startswith((b"RIFF", b"\x1aE\xdf\xa3")):
        return "a video"
    if head.lstrip()[:1] in (b"{", b"["):
        return "a JSON file"
    return None


def check_output_path(out: Path, inputs: list[Path], writes: str | None) -> None:
    """Refuse, before any work, an output that is one of the command's input files, or an
    existing non-empty file of another kind than the ``writes`` it will hold (``ingest m.mp4
    -o m.mp4``, ``split -o some.mp4``)."""
    if not out.is_file():
        return
    if any(p.is_file() and os.path.samefile(p, out) for p in inputs):
        raise OutputError("is also an input of this command: not writing over it", out)
    if writes is not None and out.stat().st_size and (kind := file_kind(out)) != writes:
        raise OutputError(
            f"holds {kind or 'a file of another kind'} and this command writes {writes}: not "
            "replacing it (choose another output name, or remove the file)",
            out,
        )


def check_command_paths(stage: object, settings: object) -> list[Path]:
    """:func:`check_output_path` of every output of a command (:func:`command_outputs`), its
    inputs being the settings that name existing files; returns those outputs."""
    outs = command_outputs(stage, settings)
    names = [Path(str(o)) for o in getattr(stage, "outputs", ())]
    inputs = []
    for name, value in vars(settings).items():
        if name in OUTPUT_SETTINGS or name == getattr(stage, "folder", None):
            continue
        for v in value if isinstance(value, list) else [value]:
            if isinstance(v, str) and v and Path(v).is_file():
                inputs.append(Path(v))
    for i, out in enumerate(outs):
        writes = FILE_KINDS.get(names[i].suffix) if i < len(names) else None
        check_output_path(out, inputs, writes)
    return outs


def command_outputs(stage: object, settings: object) -> list[Path]:
    """The outputs a command's ``settings`` will write: its ``output`` / ``out`` / folder setting
    when given, else the registry entry ``stage``'s conventional names in its workspace."""
    names = (*OUTPUT_SETTINGS, getattr(stage, "folder", None))
    given = [getattr(settings, n) for n in names if n and getattr(settings, n, None)]
    if given:
        return [Path(str(v)) for v in dict.fromkeys(given)]
    workdir = Path(getattr(settings, "workdir", None) or ".")
    return [workdir / o for o in getattr(stage, "outputs", ()) if "RUN_DIR" not in o]


@contextlib.contextmanager
def output_locks(paths: list[Path], wait: bool | None = None) -> Iterator[None]:
    """:func:`output_lock` of every path in ``paths`` (in sorted order: no deadlock)."""
    with contextlib.ExitStack() as stack:
        for p in sorted({Path(p).absolute() for p in paths}):
            stack.enter_context(output_lock(p, wait))
        yield


@contextlib.contextmanager
def atomic_output(
    path: str | Path, replaceable: Callable[[str], bool] | None = None
) -> Iterator[Path]:
    """Yield a temporary path beside ``path``; rename it onto ``path`` only if the block succeeds.

    An exception (or Ctrl-C) inside the block removes the temporary file, so a reader never sees
    a half-written output under the final name, and an existing output is kept. Temporaries of
    ``path`` left by a killed process (``kill -9``) are removed when the next writer starts.
    Works for files and for directories: an existing folder is replaced only by a folder, and
    only when everything in it is something the new folder holds too or ``replaceable(name)``
    allows (a folder output pointed at a workspace never deletes the user's files).

    Raises:
        OutputError: the storage refused (full disk, read-only, a file or folder in the way),
            or an existing folder holds files this output does not own.
    """
    final = Path(path)
    if final.name in ("", ".", ".."):
        raise OutputError("is not a file or folder name to write to", path)
    if final.is_dir() and final.resolve() in (Path.cwd().resolve(), *Path.cwd().resolve().parents):
        raise OutputError("is the current folder or one of its parents: not replacing it", path)
    stack = contextlib.ExitStack()  # holds the output's lock
    tmp = final.with_name(f".{final.name}.tmp-{os.getpid()}")
    old = final.with_name(f".{final.name}.old-{os.getpid()}")
    try:
        stack.enter_context(output_lock(final, wait=True))
        final.parent.mkdir(parents=True, exist_ok=True)
        _remove_stale_temporaries(final)
        yield tmp
        if final.is_dir() and not final.is_symlink():
            if not tmp.is_dir():
                raise OutputError("is a folder, expected a file", final)
            _check_foreign(final, tmp, replaceable)
            os.replace(final, old)  # kept until the new folder is in place
            try:
                os.replace(tmp, final)
            except OSError:
                os.replace(old, final)
                raise
            _remove(old)
            return
        if final.exists() and tmp.is_dir():
            raise OutputError("is a file, expected a folder", final)
        os.replace(tmp, final)
    except OSError as err:
        reason = storage_error(err)
        if reason is None:
            raise
        where = getattr(err, "filename", None)
        shown = final if where in (None, str(tmp)) else Path(where)
        raise OutputError(f"cannot write: {reason}", shown) from None
    finally:
        with contextlib.suppress(OSError):
            _remove(tmp)
        stack.close()


def _check_foreign(final: Path, new: Path, replaceable: Callable[[str], bool] | None) -> None:
    """Refuse to replace folder ``final`` while it holds names the ``new`` folder does not."""
    mine = {p.name for p in new.iterdir()}
    foreign = sorted(
        p.name
        for p in final.iterdir()
        if p.name not in mine and not (replaceable is not None and replaceable(p.name))
    )
    if foreign:
        shown = ", ".join(foreign[:3]) + (", ..." if len(foreign) > 3 else "")
        raise OutputError(
            f"holds {shown}, which this output does not write: not replacing it (move them, "
            "or write elsewhere)",
            final,
        )


def _remove_stale_temporaries(final: Path) -> None:
    """Clean up after writers of ``final`` that were killed (``kill -9``) or are this process:
    their temporaries are removed, and a replaced folder kept aside is put back when ``final``
    is missing (the kill fell between the two renames). A live writer's files are left alone."""
    for p in sorted(final.parent.glob(f".{glob.escape(final.name)}.*-*")):
        kind, _, pid = p.name[len(final.name) + 2 :].partition("-")
        if kind not in ("tmp", "old") or not pid.isdigit():
            continue
        if int(pid) != os.getpid() and _alive(int(pid)):
            continue
        if kind == "old" and not final.exists():
            os.replace(p, final)
        else:
            _remove(p)


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def require_free_space(path: str | Path, nbytes: int) -> None:
    """Raise :class:`OutputError` when the filesystem that will hold ``path`` has fewer than
    ``nbytes`` bytes free (checked before large writes: HDF5 can crash on a full disk)."""
    p = Path(path).absolute()
    probe = p.parent
    while not probe.exists() and probe != probe.parent:
        probe = probe.parent
    if not probe.is_dir():
        raise OutputError("a parent of the path is a file, not a folder", path)
    free = shutil.disk_usage(probe).free
    if free < nbytes:
        raise OutputError(
            f"cannot write: needs about {nbytes / 1e6:.1f} MB, {free / 1e6:.1f} MB free on the "
            "device",
            path,
        )


def _remove(p: Path) -> None:
    if p.is_dir() and not p.is_symlink():
        shutil.rmtree(p, ignore_errors=True)
    else:
        with contextlib.suppress(FileNotFoundError):
            p.unlink()


def sha256_file(path: str | Path, chunk: int = 1 << 20) -> str:
    """Hex SHA-256 of a file's bytes (or of a directory's files, sorted by relative name)."""
    p = Path(path)
    h = hashlib.sha256()
    files = sorted(q for q in p.rglob("*") if q.is_file()) if p.is_dir() else [p]
    for f in files:
        if p.is_dir():
            h.update(str(f.relative_to(p)).encode())
        with open(f, "rb") as fh:
            while block := fh.read(chunk):
                h.update(block)
    return h.hexdigest()
