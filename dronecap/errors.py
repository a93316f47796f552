"""The one exception type that the CLI turns into a one-line message and a non-zero exit.

Every stage raises :class:`InputError` (or a subclass) for problems with what the user gave it:
a missing or foreign file, an impossible request, data that cannot be reconstructed. The message
names the file and the problem. Anything else that escapes is a bug and keeps its traceback.
"""

from __future__ import annotations

from pathlib import Path


class InputError(Exception):
    """A problem with the user's input; ``str(err)`` is the whole one-line message."""

    def __init__(self, message: str, path: str | Path | None = None) -> None:
        self.path = None if path is None else Path(path)
        super().__init__(f"{path}: {message}" if path is not None else message)
