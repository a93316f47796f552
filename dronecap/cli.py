"""The ``dronecap`` command line: a table of sub-commands, each imported only when it runs.

Each entry names a module in :mod:`dronecap.commands` that defines

    HELP: str                                    one-line description
    add_arguments(parser: ArgumentParser) -> None
    run(args: Namespace) -> int                  exit code

Command modules import only the standard library at module level, so ``dronecap --help`` stays
fast; torch, pycolmap, open3d and Flower are imported inside ``run``. An :class:`InputError`
raised anywhere becomes one line on stderr and exit code 1, and so does an OSError of the
storage (full disk, read-only, a folder in the way: ``dronecap.files.storage_error``); Ctrl-C
exits with 130.
"""

from __future__ import annotations

import argparse
import importlib
import sys
from typing import NoReturn

# name -> (module, one-line help). The help is repeated here so `--help` imports nothing.
COMMANDS: dict[str, tuple[str, str]] = {
    "simulate": ("simulate", "render a synthetic nano-drone flight video with ground truth"),
    "ingest": ("ingest", "decode a flight video to 160x160 gray, select frames -> frames.h5"),
    "calibrate": ("calibrate", "calibrate a camera from images or a video of a board"),
    "sfm": ("sfm", "recover camera poses with COLMAP, normalise and bound -> posed.h5"),
    "split": ("split", "train/test split of a posed flight -> dataset.h5"),
    "shard": ("shard", "IID or viewpoint-sector shards, one file per drone -> shards/"),
    "import-blender": ("import_blender", "NeRF Synthetic 360 scene -> dataset.h5"),
    "import-transforms": ("import_transforms", "instant-ngp/nerfstudio dataset -> dataset.h5"),
    "import-colmap": ("import_colmap", "COLMAP sparse model + images -> dataset.h5"),
    "export-transforms": ("export_transforms", "dataset -> transforms.json + images"),
    "train": ("train", "train Tiny-DroNeRF on a dataset -> run dir"),
    "render": ("render", "render views (test poses or an orbit) of a trained run"),
    "export-geometry": ("export_geometry", "mesh and point cloud (PLY) of a trained run"),
    "eval": ("eval", "re-evaluate a trained run on its test views (PSNR/SSIM)"),
    "cost": ("cost", "GAP9 memory/compute/latency/energy report for a configuration"),
    "federate": ("federate", "FedAvg across drones on Flower"),
    "run": ("run", "run a pipeline from pipelines.yaml with caching"),
}


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
    sub = p.add_subparsers(dest="command", metavar="COMMAND")
    for name, (_, help_) in COMMANDS.items():
        sub.add_parser(name, help=help_, add_help=False)
    return p


def build_parser(name: str) -> tuple[argparse.ArgumentParser, object]:
    """The full parser of one sub-command and its module (imports that module)."""
    module = importlib.import_module(f"dronecap.commands.{COMMANDS[name][0]}")
    p = _OneLineParser(
        prog=f"dronecap {name}", description=module.HELP, formatter_class=_HelpWithDefaults
    )
    p.add_argument(
        "--workdir",
        default=".",
        help="workspace folder where inputs/outputs are found by conventional names (default: .)",
    )
    module.add_arguments(p)
    return p, module


def main(argv: list[str] | None = None) -> int:
    """Entry point of the console script; returns the exit code."""
    argv = list(sys.argv[1:] if argv is None else argv)
    while argv and argv[0] in VERBOSITY:
        _set_verbosity(VERBOSITY[argv.pop(0)])
    if not argv or argv[0] not in COMMANDS:
        _top_parser().parse_args(argv or ["--help"])
        return 2
    from dronecap.errors import InputError

    parser, module = build_parser(argv[0])
    args = parser.parse_intermixed_args(argv[1:])
    try:
        return int(module.run(args) or 0)
    except InputError as err:
        print(f"dronecap {argv[0]}: error: {err}", file=sys.stderr)
        return 1
    except OSError as err:  # a storage failure outside atomic_output: one line, else a bug
        from dronecap.files import storage_error

        reason = storage_error(err)
        if reason is None:
            raise
        where = f"{err.filename}: " if err.filename else ""
        print(f"dronecap {argv[0]}: error: {where}{reason}", file=sys.stderr)
        return 1
    except ModuleNotFoundError as err:
        extra = OPTIONAL_MODULES.get((err.name or "").split(".")[0])
        if extra is None:
            raise
        print(
            f"dronecap {argv[0]}: error: needs {err.name}, an optional part of dronecap: "
            f"pip install 'dronecap[{extra}]'",
            file=sys.stderr,
        )
        return 1
    except KeyboardInterrupt:
        print(
            f"dronecap {argv[0]}: interrupted (outputs written so far are complete)",
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
