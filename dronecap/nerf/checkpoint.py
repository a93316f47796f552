"""Atomic checkpoint files of plain data: tensors, numbers, strings, lists and dicts.

A checkpoint is read with ``torch.load(weights_only=True)``: its pickle may only rebuild tensors
and primitive containers, so a run folder from someone else cannot run code when ``eval``,
``render`` or ``export-geometry`` open it. numpy arrays in the payload are written as tensors
(tagged ``{NUMPY_TAG: tensor}``) and given back as numpy arrays. Checkpoints written before
that held pickled numpy arrays; those of plain numeric dtypes are still read (the numpy
rebuild functions for those dtypes are allowed, nothing else). Any other file is refused with
one line saying how to convert it, once, if the user trusts it::

    python -m dronecap.nerf.checkpoint --trust RUN/checkpoint.pt
"""

from __future__ import annotations

import argparse
import pickle
import re
import sys
from pathlib import Path, PurePath
from typing import Any

import numpy as np
import torch

from dronecap.errors import InputError
from dronecap.files import atomic_output

from .resolve import Resolved, legacy_resolved

CHECKPOINT_VERSION = 1
NUMPY_TAG = "__numpy__"
CONVERT = "python -m dronecap.nerf.checkpoint --trust"
# What older checkpoints' numpy arrays need to be rebuilt: plain numeric dtypes only (an object
# array would need further globals, which stay refused).
_NUMPY_GLOBALS = [
    np._core.multiarray._reconstruct,
    np._core.multiarray.scalar,
    np.ndarray,
    np.dtype,
    *(
        type(np.dtype(t))
        for t in (np.bool_, np.uint8, np.int8, np.int16, np.int32, np.int64, np.float16)
        + (np.float32, np.float64)
    ),
]


def _plain(obj: Any) -> Any:
    """``obj`` with every numpy array replaced by ``{NUMPY_TAG: tensor}``, numpy scalars by
    Python numbers and paths by strings (recursively)."""
    if isinstance(obj, np.ndarray):
        return {NUMPY_TAG: torch.from_numpy(np.ascontiguousarray(obj))}
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, PurePath):
        return str(obj)
    if isinstance(obj, dict):
        return {k: _plain(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return type(obj)(_plain(v) for v in obj)
    return obj


def _numpy_back(obj: Any) -> Any:
    """Inverse of :func:`_plain`."""
    if isinstance(obj, dict):
        if set(obj) == {NUMPY_TAG} and isinstance(obj[NUMPY_TAG], torch.Tensor):
            return obj[NUMPY_TAG].numpy()
        return {k: _numpy_back(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return type(obj)(_numpy_back(v) for v in obj)
    return obj


def write_checkpoint(path: str | Path, payload: dict[str, Any]) -> None:
    """Write ``payload`` to ``path`` atomically (a reader never sees a partial file), as data
    that :func:`read_checkpoint` loads without executing anything."""
    with atomic_output(path) as tmp:
        torch.save(_plain({"version": CHECKPOINT_VERSION, **payload}), tmp)


def read_checkpoint(path: str | Path) -> dict[str, Any]:
    """Read a checkpoint written by :func:`write_checkpoint`, never running code from it.

    Raises:
        InputError: missing, unreadable, not of this version, or a pickle that asks for
            anything but tensors, plain containers and numeric numpy arrays (the line says how
            to convert a trusted file).
    """
    path = Path(path)
    if not path.exists():
        raise InputError("no checkpoint here (train first)", path)
    if not path.is_file():
        raise InputError("is not a regular file", path)
    try:
        with torch.serialization.safe_globals(_NUMPY_GLOBALS):
            ck = torch.load(path, map_location="cpu", weights_only=True)
    except pickle.UnpicklingError as err:
        found = re.search(r"GLOBAL ([\w.]+)", str(err))
        what = f" ({found.group(1)})" if found else ""
        raise InputError(
            f"refusing to load: it holds Python objects that loading would run{what}, not only "
            f"weights; if you trust this file, convert it once: {CONVERT} {path}",
            path,
        ) from None
    except Exception as err:  # truncated or foreign file
        first = (str(err).strip().splitlines() or [type(err).__name__])[0]
        raise InputError(f"not a readable checkpoint: {first}", path) from None
    if not isinstance(ck, dict) or ck.get("version") != CHECKPOINT_VERSION:
        raise InputError("not a dronecap checkpoint of this version", path)
    return _numpy_back(ck)


def checkpoint_resolved(ck: dict[str, Any], path: str | Path) -> Resolved:
    """The resolved configuration of checkpoint ``ck`` (read from ``path``); a checkpoint
    written before resolved configs (a ``config`` and a ``scene``) gets it re-derived.
    InputError when it holds neither."""
    try:
        if "resolved" in ck:
            return Resolved.from_dict(ck["resolved"])
        return legacy_resolved(ck["config"], ck["scene"])
    except (KeyError, TypeError, ValueError) as err:
        raise InputError(f"checkpoint has no usable configuration ({err})", path) from None


def convert_trusted(path: str | Path) -> None:
    """Rewrite a checkpoint the user trusts (one that :func:`read_checkpoint` refuses) as plain
    data. This unpickles it the unsafe way: only for files from a trusted source."""
    path = Path(path)
    ck = torch.load(path, map_location="cpu", weights_only=False)  # noqa: S614 (the user trusts it)
    if not isinstance(ck, dict) or ck.get("version") != CHECKPOINT_VERSION:
        raise InputError("not a dronecap checkpoint of this version", path)
    write_checkpoint(path, {k: v for k, v in ck.items() if k != "version"})
    read_checkpoint(path)  # what was written must load the safe way


def main(argv: list[str] | None = None) -> int:
    """``python -m dronecap.nerf.checkpoint --trust PATH...``: convert trusted checkpoints."""
    ap = argparse.ArgumentParser(
        prog="python -m dronecap.nerf.checkpoint",
        description="Rewrite old checkpoints you trust as plain tensors (loading them runs "
        "whatever code they hold: only for files from a trusted source).",
    )
    ap.add_argument("paths", nargs="+", type=Path, help="checkpoint.pt files or run folders")
    ap.add_argument("--trust", action="store_true", required=True, help="I trust these files")
    args = ap.parse_args(argv)
    for p in args.paths:
        target = p / "checkpoint.pt" if p.is_dir() else p
        try:
            convert_trusted(target)
        except InputError as err:
            print(f"convert-checkpoint: error: {err}", file=sys.stderr)
            return 1
        except (OSError, pickle.UnpicklingError, RuntimeError) as err:
            print(f"convert-checkpoint: error: {target}: {err}", file=sys.stderr)
            return 1
        print(f"converted {target}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
