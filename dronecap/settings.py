"""Stage settings, declared: each stage's settings are one dataclass whose fields carry their
own help.

A command module in :mod:`dronecap.commands` defines ``Settings`` (a dataclass deriving from
:class:`Settings`, one :func:`setting` per option) and ``run(settings) -> int``. Adding an
option is one line in the stage's ``Settings``::

    every: int = setting(8, help="hold out one frame in EVERY for test", minimum=2)

An existing domain dataclass (``TrainConfig``, ``SelectionParams``, ``SfmOptions``) is not
copied: :func:`flatten` exposes its fields as options whose given values reach ``run`` as a
``{field: value}`` dict of overrides. :class:`TorchSettings` and :class:`ProgressSettings` are
the settings several stages share. :mod:`dronecap.settings_cli` turns these declarations into
command-line options and pipeline parameters.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from dataclasses import MISSING, dataclass, field
from typing import Any

KEY = "dronecap"  # the field-metadata key of a setting


@dataclass(frozen=True)
class Meta:
    """How one settings field appears on the command line (see :func:`setting`)."""

    help: str
    flag: str | None = None
    short: str | None = None
    positional: bool = False
    choices: tuple[Any, ...] | None = None
    minimum: float | None = None
    maximum: float | None = None
    metavar: str | None = None
    const: str | None = None
    parse: Callable[[str], Any] | None = None
    repeat: bool = False
    group: str | None = None
    flat: Flat | None = None
    late: bool = False


@dataclass(frozen=True)
class Flat:
    """The fields of a domain dataclass exposed as options (see :func:`flatten`)."""

    cls: type
    help: Callable[[dataclasses.Field], str]
    parse: Callable[[str, str], Any] | None = None  # (field name, text) -> value
    only: tuple[str, ...] | None = None  # exposed fields (default: all)
    flags: dict[str, str] = field(default_factory=dict)  # field -> option name, when not its own


def setting(
    default: Any = MISSING,
    *,
    help: str,  # noqa: A002 - argparse's word
    factory: Callable[[], Any] | None = None,
    flag: str | None = None,
    short: str | None = None,
    positional: bool = False,
    choices: tuple[Any, ...] | None = None,
    minimum: float | None = None,
    maximum: float | None = None,
    metavar: str | None = None,
    const: str | None = None,
    parse: Callable[[str], Any] | None = None,
    repeat: bool = False,
    group: str | None = None,
    late: bool = False,
) -> Any:
    """A settings field: its default (none: required), help and how it is given.

    Args:
        flag: long option when not ``--field-name`` (e.g. ``--loop-images``).
        short: a short alias (``-o``).
        positional: an argument, not an option (optional when its default is None; a list
            takes any number).
        choices: the allowed values (after ``parse``).
        minimum, maximum: bounds of a number, checked by :func:`check`.
        const: the value of an option given without one (``--noise`` alone).
        parse: text -> value, when not the field's type (e.g. ``str.upper``).
        repeat: a list option given once per value (``--set a=1 --set b=2``); otherwise a
            list option takes several values after one flag.
        group: the ``--help`` section.
        late: ``parse`` runs when the settings are built, so a value it refuses is a one-line
            error naming the option (exit code 1, like a value out of bounds), not argparse's;
            ``const`` is then text that ``parse`` converts too.
    """
    meta = Meta(help, flag, short, positional, choices, minimum, maximum, metavar, const, parse,
                repeat, group, late=late)  # fmt: skip
    if factory is not None:
        return field(default_factory=factory, metadata={KEY: meta})
    return field(default=default, metadata={KEY: meta})


def flatten(
    cls: type,
    *,
    help: Callable[[dataclasses.Field], str],  # noqa: A002
    parse: Callable[[str, str], Any] | None = None,
    only: tuple[str, ...] | None = None,
    flags: dict[str, str] | None = None,
    group: str | None = None,
) -> Any:
    """A field holding overrides of domain dataclass ``cls``: one option per field of ``cls``
    (or of ``only``), named after the field unless ``flags`` renames it; its value is the dict
    of the fields given (``{}``: all as ``cls`` defines them).

    ``help`` gives an option's help from the field; ``parse(name, text)`` converts a value
    (default: the field's type).
    """
    flat = Flat(cls, help, parse, only, dict(flags or {}))
    return field(default_factory=dict, metadata={KEY: Meta("", group=group, flat=flat)})


def input_setting(what: str, default: str) -> Any:
    """A stage's optional positional input: ``what`` it reads, ``default`` when not given (a
    conventional name in the workspace)."""
    return setting(None, positional=True, help=f"{what} (default: {default})")


def output_setting(what: str, default: str) -> Any:
    """A stage's ``-o``/``--output``: ``what`` it writes, ``default`` when not given (a
    conventional name in the workspace or the run folder)."""
    return setting(None, short="-o", help=f"{what} (default: {default})")


class Numbers(tuple):
    """Numbers given as one comma-separated value (``--noise 3,0.3``) and shown the same way,
    so :func:`dronecap.settings_cli.command_line` gives back what was typed."""

    separator = ","

    def __str__(self) -> str:
        return self.separator.join(str(x) for x in self)


class Size(Numbers):
    """An image size in pixels, (width, height), given and shown as ``WxH``."""

    separator = "x"


def numbers(*counts: int) -> Callable[[str], Numbers]:
    """A ``parse=`` for ``counts`` (one of them) comma-separated finite numbers, as floats."""
    import math

    want = (
        "a number" if counts == (1,) else " or ".join(map(str, counts)) + " comma-separated numbers"
    )

    def parse(text: str) -> Numbers:
        try:
            values = tuple(float(x) for x in text.split(","))
        except ValueError:
            values = ()
        if len(values) not in counts or not all(math.isfinite(v) for v in values):
            raise ValueError(f"takes {want}, got {text!r}")
        return Numbers(values)

    return parse


@dataclass(kw_only=True)
class Settings:
    """What every stage takes: the workspace its conventional file names are found in."""

    workdir: str = setting(
        ".", help="workspace folder where inputs/outputs are found by conventional names"
    )


@dataclass(kw_only=True)
class TorchSettings(Settings):
    """A stage that runs torch: how many CPU threads."""

    threads: int | None = setting(
        None, help="torch CPU threads (default: the cores not already busy)"
    )  # checked by dronecap.cpu.check_threads


@dataclass(kw_only=True)
class ProgressSettings(Settings):
    """A stage with a progress bar it can hide."""

    no_progress: bool = setting(False, help="no progress bar")
