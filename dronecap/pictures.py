"""The pictures of each stage in a pipeline report, drawn from the files the stage wrote.

Each picture is ``(stage_dir, params, out) -> Path | None`` (None: nothing to draw) and is named
in the stage's registry entry (:attr:`dronecap.registry.Stage.pictures`), so a stage's pictures
are declared once: the ingest contact sheet of kept frames, the SfM trajectory (against the
ground truth when the stage was given one), the training curve, the labelled
truth | render | error comparison and the fly-through of the test views in flight order
(animated WebP, which browsers play). Heavy imports happen inside the functions: the registry
imports this module and ``dronecap --help`` stays fast.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Any

from dronecap import workspace as ws
from dronecap.files import atomic_output

if TYPE_CHECKING:
    import numpy as np

SHEET_FRAMES = 24  # frames on the ingest contact sheet
FLYTHROUGH_MS = 250  # frame duration of the fly-through (ms)
RENDERS = "renders"  # a training run's test renders (test_NNN.png), nerf.run_dir.RENDERS


def kept_frames(stage_dir: Path, params: dict[str, Any], out: Path) -> Path | None:
    """Ingest: a 6-wide grid of evenly spaced kept frames, with their source names."""
    frames = stage_dir / ws.FRAMES
    return _contact_sheet(frames, out) if frames.exists() else None


def trajectory(stage_dir: Path, params: dict[str, Any], out: Path) -> Path | None:
    """SfM: the recovered flight, with the ground truth the stage was given (``gt``)."""
    from dronecap.sfm.plots import trajectory_plot

    posed = stage_dir / ws.POSED
    if not posed.exists():
        return None
    gt = params.get("gt")
    return trajectory_plot(posed, out, gt if isinstance(gt, str) and Path(gt).exists() else None)


def training_curve(stage_dir: Path, params: dict[str, Any], out: Path) -> Path | None:
    """Train: PSNR and loss against the step and the training time."""
    from dronecap.plots import training_curve as draw

    metrics = stage_dir / ws.METRICS
    return draw(metrics, out) if metrics.exists() else None


def truth_render_error(stage_dir: Path, params: dict[str, Any], out: Path) -> Path | None:
    """Train: ground truth | render | error of the first test views of its ``dataset``."""
    dataset = params.get("dataset")
    if not (isinstance(dataset, str) and Path(dataset).exists()):
        return None
    return _truth_render_error(stage_dir, Path(dataset), out)


def flythrough(stage_dir: Path, params: dict[str, Any], out: Path) -> Path | None:
    """Train: its test renders in flight order (animated WebP)."""
    return _flythrough(stage_dir, out)


def _contact_sheet(frames_h5: Path, out: Path) -> Path | None:
    """A 6-wide grid of evenly spaced kept frames, with their source names."""
    import cv2
    import numpy as np

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
    """Encode a BGR uint8 [H, W, 3] image as PNG and write it atomically."""
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
    import numpy as np

    from dronecap.datasets.format import open_dataset

    renders = sorted((run_dir / RENDERS).glob("test_*.png"))[:n]
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

    renders = sorted((run_dir / RENDERS).glob("test_*.png"))
    if len(renders) < 2:
        return None
    frames = [Image.open(p).convert("RGB") for p in renders]
    with atomic_output(out) as tmp:
        frames[0].save(
            tmp, format="WEBP", save_all=True, append_images=frames[1:],
            duration=FLYTHROUGH_MS, loop=0, quality=85,
        )  # fmt: skip
    return out
