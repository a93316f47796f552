"""The one exception type that the CLI turns into a one-line message and a non-zero exit.

Every stage raises :class:`InputError` (or a subclass) for problems with what the user gave it:
a missing or foreign file, an impossible request, data that cannot be reconstructed, an output
path that cannot be written (:class:`OutputError`). The message names the file and the problem.
Anything else that escapes is a bug and keeps its traceback.
"""

from __future__ import annotations

from pathlib import Path


class InputError(Exception):
    """A problem with the user's input; ``str(err)`` is the whole one-line message."""

    def __init__(self, message: str, path: str | Path | None = None) -> None:
        self.path = None if path is None else Path(path)
        super().__init__(f"{path}: {message}" if path is not None else message)


class OutputError(InputError):
    """An output that cannot be written where the user asked: a full disk, a read-only
    filesystem, a folder where a file should go (or the reverse), no permission."""
