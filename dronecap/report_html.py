"""The pictures of a pipeline run and its self-contained ``report.html``.

:func:`stage_pictures` makes (once) and lists the pictures worth looking at for each stage:
the kept frames of ``ingest`` as a contact sheet, the recovered trajectory of ``sfm`` (against
the ground truth when the stage was given one), the training curve, the labelled
truth | render | error comparison and a fly-through of the test views in flight order
(animated WebP, which browsers play) of ``train``. :func:`write_html` embeds them all in one HTML
file (base64 images), so the report opens anywhere without the run folder.
"""

from __future__ import annotations

import base64
import html
from pathlib import Path
from typing import Any

import numpy as np

from dronecap.files import atomic_output

PICTURES = "pictures"  # folder of the generated pictures, inside the pipeline's folder
SHEET_FRAMES = 24  # frames on the ingest contact sheet
FLYTHROUGH_MS = 250  # frame duration of the fly-through (ms)


def _contact_sheet(frames_h5: Path, out: Path) -> Path | None:
    """A 6-wide grid of evenly spaced kept frames, with their source names."""
    import cv2

    from dronecap.datasets.format import open_dataset

    ds = open_dataset(frames_h5)
    if ds.n == 0:
        return None
    idx = np.unique(np.linspace(0, ds.n - 1, min(SHEET_FRAMES, ds.n)).astype(int))
    tiles = []
    for i in idx:
        img = ds.images[i]
        img = cv2.cvtColor(img, cv2.COLOR_GRAY2BGR) if img.shape[2] == 1 else img[..., ::-1]
        img = np.ascontiguousarray(img)
        cv2.putText(img, ds.frame_name(int(i))[-14:], (2, 12), 0, 0.35, (0, 255, 255), 1)
        tiles.append(img)
    h, w = tiles[0].shape[:2]
    cols = 6
    while len(tiles) % cols:
        tiles.append(np.zeros((h, w, 3), np.uint8))
    rows = [np.concatenate(tiles[r : r + cols], 1) for r in range(0, len(tiles), cols)]
    return _write_png(out, np.concatenate(rows, 0))


def _write_png(path: Path, bgr: np.ndarray) -> Path:
    import cv2

    ok, buf = cv2.imencode(".png", bgr)
    if not ok:
        raise RuntimeError(f"PNG encoding failed for {path}")
    with atomic_output(path) as tmp:
        tmp.write_bytes(buf.tobytes())
    return path


def _truth_render_error(run_dir: Path, dataset_h5: Path, out: Path, n: int = 4) -> Path | None:
    """Rows of ground truth | render | absolute error (x4) of the first test views, labelled."""
    import cv2

    from dronecap.datasets.format import open_dataset

    renders = sorted((run_dir / "renders").glob("test_*.png"))[:n]
    if not renders:
        return None
    ds = open_dataset(dataset_h5)
    rows = []
    for p in renders:
        i = int(p.stem.split("_")[1])
        pred = cv2.imread(str(p), cv2.IMREAD_COLOR)
        gt = ds.images[i]
        gt = cv2.cvtColor(gt, cv2.COLOR_GRAY2BGR) if gt.shape[2] == 1 else gt[..., ::-1].copy()
        if ds.alpha is not None:  # composited on the dataset's background, as the renders are
            a = ds.alpha[i][..., None].astype(np.float32) / 255.0
            bg = 255.0 * np.resize(np.asarray(ds.background or (0.0,), np.float32)[::-1], 3)
            gt = (gt * a + bg * (1 - a) + 0.5).astype(np.uint8)
        err = np.clip(np.abs(pred.astype(np.int16) - gt.astype(np.int16)) * 4, 0, 255)
        rows.append(np.concatenate([gt, pred, err.astype(np.uint8)], 1))
    grid = np.concatenate(rows, 0)
    w = rows[0].shape[1] // 3
    bar = np.full((18, grid.shape[1], 3), 255, np.uint8)
    for k, label in enumerate(("ground truth", "render", "|error| x4")):
        cv2.putText(bar, label, (k * w + 4, 13), 0, 0.4, (0, 0, 0), 1)
    return _write_png(out, np.concatenate([bar, grid], 0))


def _flythrough(run_dir: Path, out: Path) -> Path | None:
    """The test renders in flight order as an animated WebP (browsers play it)."""
    from PIL import Image

    renders = sorted((run_dir / "renders").glob("test_*.png"))
    if len(renders) < 2:
        return None
    frames = [Image.open(p).convert("RGB") for p in renders]
    with atomic_output(out) as tmp:
        frames[0].save(
            tmp, format="WEBP", save_all=True, append_images=frames[1:],
            duration=FLYTHROUGH_MS, loop=0, quality=85,
        )  # fmt: skip
    return out


def stage_pictures(command: str, stage_dir: Path, params: dict[str, Any], pics: Path) -> list:
    """Make the pictures of one stage under ``pics`` and return their paths (existing ones)."""
    from dronecap import plots
    from dronecap.sfm.plots import trajectory_plot

    made: list[Path | None] = []
    sid = stage_dir.name
    if command == "ingest" and (stage_dir / "frames.h5").exists():
        made.append(_contact_sheet(stage_dir / "frames.h5", pics / f"{sid}_kept_frames.png"))
    elif command == "sfm" and (stage_dir / "posed.h5").exists():
        gt = params.get("gt")
        gt = gt if isinstance(gt, str) and Path(gt).exists() else None
        made.append(trajectory_plot(stage_dir / "posed.h5", pics / f"{sid}_trajectory.png", gt))
    elif command == "train" and (stage_dir / "metrics.json").exists():
        made.append(plots.training_curve(stage_dir / "metrics.json", pics / f"{sid}_curve.png"))
        dataset = params.get("dataset")
        if isinstance(dataset, str) and Path(dataset).exists():
            made.append(
                _truth_render_error(
                    stage_dir, Path(dataset), pics / f"{sid}_truth_render_error.png"
                )
            )
        made.append(_flythrough(stage_dir, pics / f"{sid}_flythrough.webp"))
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
