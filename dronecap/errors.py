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


def check_option(
    flag: str, value: float, minimum: float | None = None, maximum: float | None = None
) -> None:
    """Raise :class:`InputError` unless ``value`` of option ``flag`` is a finite number in
    [``minimum``, ``maximum``] (either bound may be None: unbounded). Called where a command
    reads its options, before any work starts."""
    import math

    ok = isinstance(value, int | float) and not isinstance(value, bool) and math.isfinite(value)
    if ok and minimum is not None and value < minimum:
        ok = False
    if ok and maximum is not None and value > maximum:
        ok = False
    if not ok:
        bounds = []
        if minimum is not None:
            bounds.append(f">= {minimum:g}")
        if maximum is not None:
            bounds.append(f"<= {maximum:g}")
        need = " and ".join(bounds) or "a finite number"
        raise InputError(f"{flag} must be {need}, got {value!r}")
