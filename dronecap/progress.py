"""Progress of long work: a bar on a terminal, a line every few seconds in a log.

Every stage reports progress through :func:`progress_bar`, never through tqdm directly, so a
redirected log (a pipeline run, CI, ``2> log.txt``) gets one plain line at most every
``LOG_EVERY_S`` seconds instead of carriage-return bar updates. ``DRONECAP_PROGRESS`` overrides
the choice: ``bar``, ``log`` or ``off`` (``dronecap -q`` sets ``off``).
"""

from __future__ import annotations

import os
import sys
import time
from collections.abc import Iterable, Iterator
from typing import Any

LOG_EVERY_S = 10.0  # seconds between two progress lines in a log
ENV = "DRONECAP_PROGRESS"


def mode() -> str:
    """ "bar" on a terminal, "log" otherwise, or what ``DRONECAP_PROGRESS`` says."""
    forced = os.environ.get(ENV, "").strip().lower()
    if forced in ("bar", "log", "off"):
        return forced
    return "bar" if sys.stderr.isatty() else "log"


class LogProgress:
    """The tqdm subset dronecap uses (``update``, ``set_postfix``, ``close``, iteration), as
    plain lines on stderr at most every ``LOG_EVERY_S`` seconds, plus a last one at the end when
    the work lasted long enough to print any (short work stays silent)."""

    def __init__(
        self,
        iterable: Iterable | None = None,
        total: int | None = None,
        desc: str = "",
        unit: str = "it",
        initial: int = 0,
        disable: bool = False,
        every_s: float | None = None,
        **_: Any,
    ) -> None:
        self.iterable = iterable
        if total is None and iterable is not None and hasattr(iterable, "__len__"):
            total = len(iterable)  # type: ignore[arg-type]
        self.total, self.desc, self.unit, self.n = total, desc, unit, initial
        self.disable = disable
        self.every_s = LOG_EVERY_S if every_s is None else every_s
        self.t0 = self.last = time.monotonic()
        self.postfix = ""
        self.closed = False
        self.printed = False

    def __iter__(self) -> Iterator:
        for item in () if self.iterable is None else self.iterable:
            yield item
            self.update(1)
        self.close()

    def __enter__(self) -> LogProgress:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def set_postfix(self, **kv: Any) -> None:
        """Remember ``key=value`` pairs shown on the next line."""
        self.postfix = ", ".join(f"{k}={v}" for k, v in kv.items())

    def set_description(self, desc: str) -> None:
        """Change the label of the following lines."""
        self.desc = desc

    def update(self, n: int = 1) -> None:
        """Count ``n`` more units; print a line if ``every_s`` has passed since the last."""
        self.n += n
        now = time.monotonic()
        if now - self.last >= self.every_s:
            self.last = now
            self._line()

    def _line(self, final: bool = False) -> None:
        if self.disable:
            return
        self.printed = True
        dt = time.monotonic() - self.t0
        of = f"/{self.total}" if self.total is not None else ""
        rate = f", {self.n / dt:.1f} {self.unit}/s" if dt > 0 and self.n else ""
        tail = f" ({self.postfix})" if self.postfix else ""
        end = " done" if final else ""
        print(f"{self.desc}: {self.n}{of} {self.unit}{rate}, {dt:.0f} s{end}{tail}",
              file=sys.stderr, flush=True)  # fmt: skip

    def close(self) -> None:
        """Print the final line once."""
        if not self.closed:
            self.closed = True
            if self.printed:
                self._line(final=True)


def progress_bar(iterable: Iterable | None = None, **kwargs: Any):
    """A tqdm bar on a terminal, a :class:`LogProgress` otherwise (same keyword arguments:
    ``total``, ``desc``, ``unit``, ``initial``, ``disable``)."""
    m = mode()
    if m == "off":
        kwargs["disable"] = True
    if m == "bar":
        from tqdm import tqdm

        kwargs.setdefault("dynamic_ncols", True)
        return tqdm(iterable, **kwargs)
    return LogProgress(iterable, **kwargs)
