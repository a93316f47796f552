"""The pictures of a pipeline run and its self-contained ``report.html``.

:func:`stage_pictures` makes and lists the pictures the registry declares for each stage
(:attr:`dronecap.registry.Stage.pictures`, drawn by :mod:`dronecap.pictures`); :func:`write_html`
embeds them all in one HTML file (base64 images), so the report opens anywhere without the run
folder.
"""

from __future__ import annotations

import base64
import html
from pathlib import Path
from typing import Any

from dronecap.files import atomic_output

PICTURES = "pictures"  # folder of the generated pictures, inside the pipeline's folder


def stage_pictures(command: str, stage_dir: Path, params: dict[str, Any], pics: Path) -> list:
    """Make (under ``pics``) the pictures the registry declares for ``command``
    (:attr:`dronecap.registry.Stage.pictures`) from one stage's folder; their paths (those made)."""
    from dronecap.registry import STAGES

    made = [
        picture(stage_dir, params, pics / f"{stage_dir.name}_{name}")
        for name, picture in STAGES[command].pictures
    ]
    return [p for p in made if p is not None]


def _embed(path: Path) -> str:
    mime = "image/webp" if path.suffix == ".webp" else "image/png"
    data = base64.b64encode(path.read_bytes()).decode()
    return f'<img src="data:{mime};base64,{data}" alt="{html.escape(path.name)}">'


def write_html(
    out: Path, title: str, description: str, rows: list[tuple[str, ...]], pictures: dict
) -> Path:
    """One self-contained HTML page: the summary table and every stage's pictures.

    Args:
        rows: table rows (stage, status, time, key figure, why), first row the header.
        pictures: stage id -> list of picture paths.
    """
    head, *body = rows
    table = "<tr>" + "".join(f"<th>{html.escape(c)}</th>" for c in head) + "</tr>"
    table += "".join(
        "<tr>" + "".join(f"<td>{html.escape(c)}</td>" for c in r) + "</tr>" for r in body
    )
    parts = [
        "<!doctype html><meta charset='utf-8'>",
        f"<title>{html.escape(title)}</title>",
        "<style>body{font-family:sans-serif;max-width:1200px;margin:auto;padding:1em}"
        "table{border-collapse:collapse}td,th{border:1px solid #ccc;padding:3px 8px;"
        "text-align:left}img{max-width:100%;margin:4px 0;image-rendering:pixelated}</style>",
        f"<h1>{html.escape(title)}</h1><p>{html.escape(description)}</p>",
        f"<table>{table}</table>",
    ]
    for sid, paths in pictures.items():
        if paths:
            parts.append(f"<h2>{html.escape(sid)}</h2>")
            parts += [f"<figure>{_embed(p)}<figcaption>{html.escape(p.name)}</figcaption>"
                      "</figure>" for p in paths]  # fmt: skip
    with atomic_output(out) as tmp:
        tmp.write_text("\n".join(parts) + "\n")
    return out
