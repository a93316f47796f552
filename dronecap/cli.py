"""The ``dronecap`` command line, generated from the stage registry (:mod:`dronecap.registry`).

Each command's options come from its ``Settings`` dataclass
(:func:`dronecap.settings_cli.add_options`); the parsed options become a ``Settings`` that
:func:`call` hands to the command's ``run``, the same call the pipeline runner makes. Command
modules import only the standard library at module level, so ``dronecap --help`` stays fast;
torch, pycolmap, open3d and Flower are imported inside ``run``. An :class:`InputError` raised
anywhere becomes one line on stderr and exit code 1, and so does an OSError of the storage
(full disk, read-only, a folder in the way: ``dronecap.files.storage_error``); Ctrl-C exits
with 130.
"""

from __future__ import annotations

import argparse
import os
import re
import sys
from collections.abc import Callable
from typing import Any, NoReturn

from dronecap.registry import STAGES, Stage


class _HelpWithDefaults(argparse.HelpFormatter):
    """Every option's help ends with its default, unless the text already states one."""

    def _get_help_string(self, action: argparse.Action) -> str:
        text = action.help or ""
        shown = action.default not in (None, False, [], argparse.SUPPRESS)
        if shown and action.option_strings and "default" not in text:
            text += " (default: %(default)s)"
        return text


class _OneLineParser(argparse.ArgumentParser):
    """A bad option value is one line (not argparse's usage block) and exit code 2."""

    def __init__(self, **kwargs: Any) -> None:
        super().__init__(**kwargs)
        # `--distortion -0.1,0.02`: argparse takes only plain negative numbers ("-0.1") as
        # values; let comma-separated lists starting with a minus sign be values too.
        self._negative_number_matcher = re.compile(r"^-\d*\.?\d+(e-?\d+)?(,-?\d*\.?\d+(e-?\d+)?)*$")

    def error(self, message: str) -> NoReturn:
        print(f"{self.prog}: error: {message} (see `{self.prog} --help`)", file=sys.stderr)
        raise SystemExit(2)


# Optional dependencies (pyproject extras): top-level module -> the extra that installs it.
OPTIONAL_MODULES = {"open3d": "sim", "flwr": "federated", "ray": "federated"}

# Global flags, given before the command: `dronecap -q train ...`.
VERBOSITY = {"-q": "off", "--quiet": "off", "-v": "log", "--verbose": "log"}


def _top_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="dronecap",
        description="Nano-drone captures to 3D scene reconstructions.",
        epilog="Run `dronecap COMMAND --help` for a command's options.",
    )
    p.add_argument("--version", action="version", version="dronecap 0.1.0")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress output")
    p.add_argument(
        "-v", "--verbose", action="store_true", help="progress as a line every second, also in logs"
    )
    p.add_argument(
        "--wait", action="store_true", help="wait for another command writing the same output"
    )
    sub = p.add_subparsers(dest="command", metavar="COMMAND")
    for name, stage in STAGES.items():
        sub.add_parser(name, help=stage.help, add_help=False)
    return p


def build_parser(name: str) -> tuple[argparse.ArgumentParser, Stage]:
    """The full parser of one command and its registry entry (imports its module)."""
    from dronecap.settings_cli import add_options

    stage = STAGES[name]
    p = _OneLineParser(
        prog=f"dronecap {name}", description=stage.help, formatter_class=_HelpWithDefaults
    )
    add_options(p, stage.load()[0])
    return p, stage


def main(argv: list[str] | None = None) -> int:
    """Entry point of the console script; returns the exit code."""
    argv = list(sys.argv[1:] if argv is None else argv)
    while argv and argv[0] in (*VERBOSITY, "--wait"):
        flag = argv.pop(0)
        if flag == "--wait":
            os.environ["DRONECAP_WAIT"] = "1"  # dronecap.files.output_lock waits
        else:
            _set_verbosity(VERBOSITY[flag])
    if not argv or argv[0] not in STAGES:
        _top_parser().parse_args(argv or ["--help"])
        return 2
    from dronecap.settings_cli import from_namespace

    parser, stage = build_parser(argv[0])
    args = parser.parse_intermixed_args(argv[1:])
    return call(stage, lambda cls: from_namespace(cls, args))


def call(stage: Stage, settings_of: Callable[[type], Any]) -> int:
    """Build a command's settings with ``settings_of(Settings)``, check them and run it; the
    exit code, with every user-facing failure as one line on stderr."""
    from dronecap.errors import InputError
    from dronecap.files import check_command_paths, output_locks
    from dronecap.settings_cli import check

    try:
        settings_cls, run = stage.load()
        settings = settings_of(settings_cls)
        check(settings)
        with output_locks(check_command_paths(stage, settings)):  # one writer per output
            return int(run(settings) or 0)
    except InputError as err:
        print(f"dronecap {stage.name}: error: {err}", file=sys.stderr)
        return 1
    except OSError as err:  # a storage failure outside atomic_output: one line, else a bug
        from dronecap.files import storage_error

        reason = storage_error(err)
        if reason is None:
            raise
        where = f"{err.filename}: " if err.filename else ""
        print(f"dronecap {stage.name}: error: {where}{reason}", file=sys.stderr)
        return 1
    except ModuleNotFoundError as err:
        extra = OPTIONAL_MODULES.get((err.name or "").split(".")[0])
        if extra is None:
            raise
        print(
            f"dronecap {stage.name}: error: needs {err.name}, an optional part of dronecap: "
            f"pip install 'dronecap[{extra}]'",
            file=sys.stderr,
        )
        return 1
    except KeyboardInterrupt:
        print(
            f"dronecap {stage.name}: interrupted (outputs written so far are complete)",
            file=sys.stderr,
        )
        return 130


def _set_verbosity(mode: str) -> None:
    """-q: no progress at all; -v: progress lines every second even when not on a terminal."""
    import os

    from dronecap import progress

    os.environ[progress.ENV] = mode
    if mode == "log":
        progress.LOG_EVERY_S = 1.0


if __name__ == "__main__":
    sys.exit(main())
