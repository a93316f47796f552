"""Atomic checkpoint files (torch.save of plain dicts and tensors)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import torch

from dronecap.errors import InputError
from dronecap.files import atomic_output

from .resolve import Resolved, legacy_resolved

CHECKPOINT_VERSION = 1


def write_checkpoint(path: str | Path, payload: dict[str, Any]) -> None:
    """Write ``payload`` to ``path`` atomically (a reader never sees a partial file)."""
    with atomic_output(path) as tmp:
        torch.save({"version": CHECKPOINT_VERSION, **payload}, tmp)


def read_checkpoint(path: str | Path) -> dict[str, Any]:
    """Read a checkpoint written by :func:`write_checkpoint` (InputError when unusable)."""
    path = Path(path)
    if not path.exists():
        raise InputError("no checkpoint here (train first)", path)
    try:
        ck = torch.load(path, map_location="cpu", weights_only=False)
    except Exception as err:  # truncated or foreign file
        raise InputError(f"not a readable checkpoint: {err}", path) from None
    if not isinstance(ck, dict) or ck.get("version") != CHECKPOINT_VERSION:
        raise InputError("not a dronecap checkpoint of this version", path)
    return ck


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
