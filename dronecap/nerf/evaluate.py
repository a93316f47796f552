"""Test-view metrics: PSNR and SSIM with scikit-image on the stored resolution, and the
exposure-matched PSNR (a test view's own exposure fitted away, see :func:`exposure_matched`).

With a camera model (:meth:`dronecap.nerf.photometric.Photometric.recorded`) the scores are of
the render as the camera records it (lens vignetting, the view's exposure predicted from its
neighbours in time); ``psnr_radiance`` keeps the score of the plain render."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from skimage.metrics import peak_signal_noise_ratio, structural_similarity

from dronecap.datasets.format import Dataset, Intrinsics
from dronecap.progress import progress_bar

from .photometric import Photometric

RenderFn = Callable[[np.ndarray, Intrinsics], np.ndarray]  # (c2w, K) -> float32 [H, W, C]
# (frame index, render [H, W, C]) -> what the camera recorded of it [H, W, C]
RecordFn = Callable[[int, np.ndarray], np.ndarray]


def recorder(photometric: Photometric, ds: Dataset) -> RecordFn:
    """The camera model of ``ds``'s views: (frame i, render) -> what its camera recorded
    (:meth:`Photometric.recorded`), with ``ds``'s own training frames' capture times and
    drones (split 0, the rows of the gain table) to interpolate each view's exposure."""
    drones, times = ds.drones(), ds.timestamps
    train = np.zeros(0, np.int64) if ds.split is None else np.flatnonzero(ds.split == 0)
    frames = (times[train], drones[train]) if times is not None and train.size else None

    def record(i: int, image: np.ndarray) -> np.ndarray:
        when = None if times is None else (float(times[i]), int(drones[i]))
        return photometric.recorded(image, ds.camera_of(i), when, frames)

    return record


def ground_truth(ds: Dataset, i: int, background: tuple[float, ...]) -> np.ndarray:
    """Frame ``i`` as float32 [H, W, C] in [0, 1], composited on ``background`` if it has alpha."""
    img = ds.images[i].astype(np.float32) / 255.0
    if ds.alpha is not None:
        a = ds.alpha[i].astype(np.float32)[..., None] / 255.0
        img = img * a + np.asarray(background, np.float32) * (1.0 - a)
    return img


def image_metrics(pred: np.ndarray, gt: np.ndarray) -> tuple[float, float]:
    """(PSNR dB, SSIM) of two float images [H, W, C] in [0, 1] (data_range 1)."""
    psnr = float(peak_signal_noise_ratio(gt, pred, data_range=1.0))
    ssim = float(structural_similarity(gt, pred, data_range=1.0, channel_axis=2))
    return psnr, ssim


def exposure_matched(pred: np.ndarray, gt: np.ndarray) -> np.ndarray:
    """``pred`` [H, W, C] in [0, 1] times the per-channel gain that fits it to ``gt`` best in
    least squares (``sum(pred * gt) / sum(pred^2)`` per channel; 1 for an all-black channel),
    clipped to [0, 1]: the render as a camera of the view's own exposure would record it."""
    num = np.sum(pred * gt, axis=(0, 1), dtype=np.float64)
    den = np.sum(pred * pred, axis=(0, 1), dtype=np.float64)
    gain = np.where(den > 0, num / np.where(den > 0, den, 1.0), 1.0)
    return np.clip(pred * gain.astype(np.float32), 0.0, 1.0)


def exposure_matched_psnr(pred: np.ndarray, gt: np.ndarray) -> float:
    """PSNR (dB, data_range 1) of :func:`exposure_matched` ``pred`` against ``gt`` [H, W, C]."""
    return float(peak_signal_noise_ratio(gt, exposure_matched(pred, gt), data_range=1.0))


def scores_line(test: dict) -> str:
    """The one-line summary the commands print of an evaluation result (:func:`evaluate_views`):
    PSNR, the exposure-matched PSNR when recorded, the plain render's PSNR when the camera
    model changed it, SSIM and the view count."""
    psnr = f"test PSNR {test['psnr']:.2f} dB"
    others = []
    if test.get("psnr_exposure_matched") is not None:
        others.append(f"exposure-matched {test['psnr_exposure_matched']:.2f}")
    radiance = test.get("psnr_radiance")
    if radiance is not None and abs(radiance - test["psnr"]) >= 0.005:
        others.append(f"render alone {radiance:.2f}")
    if others:
        psnr += f" ({', '.join(others)})"
    return f"{psnr}, SSIM {test['ssim']:.3f} over {test['views']} views"


def test_views(ds: Dataset) -> np.ndarray:
    """Indices of the test split (split 2), else the validation split, else none."""
    if ds.split is None:
        return np.zeros(0, np.int64)
    for s in (2, 1):
        idx = np.flatnonzero(ds.split == s)
        if idx.size:
            return idx
    return idx


def evaluate_views(
    render: RenderFn,
    ds: Dataset,
    background: tuple[float, ...],
    views=None,
    progress: bool = False,
    keep_images: bool = False,
    record: RecordFn | None = None,
) -> dict:
    """Render and score views of ``ds``.

    Args:
        render: (c2w [4, 4], intrinsics) -> float32 [H, W, C].
        ds: dataset with poses and intrinsics.
        background: colour the ground truth is composited on (and the renders use).
        views: frame indices (default: all test views, see :func:`test_views`).
        keep_images: also return the renders under "images".
        record: the camera model: PSNR and SSIM score ``record(i, render)`` (None: the
            render itself).

    Returns:
        {"psnr": mean, "ssim": mean, "psnr_exposure_matched": mean, "psnr_radiance": mean,
        "ssim_radiance": mean, "views": n, "per_view": [{the same per view, "index"}]}; the
        exposure-matched PSNR scores each render after the least-squares per-channel gain to
        its ground truth (:func:`exposure_matched`: a real test view has its own exposure),
        ``psnr_radiance`` / ``ssim_radiance`` the render itself (= ``psnr`` / ``ssim``
        without ``record``: what to compare with noise-free renders of the scene).
    """
    idx = test_views(ds) if views is None else np.asarray(views, np.int64)
    per_view, images = [], []
    for i in progress_bar(idx, desc="evaluate", unit="view", disable=not progress):
        pred = render(ds.poses[i], ds.camera_of(i))
        gt = ground_truth(ds, int(i), background)
        p, s = image_metrics(pred if record is None else record(int(i), pred), gt)
        p_alone, s_alone = (p, s) if record is None else image_metrics(pred, gt)
        per_view.append({
            "index": int(i), "psnr": p, "ssim": s,
            "psnr_exposure_matched": exposure_matched_psnr(pred, gt),
            "psnr_radiance": p_alone, "ssim_radiance": s_alone,
        })  # fmt: skip
        if keep_images:
            images.append(pred)
    out = {
        key: float(np.mean([v[key] for v in per_view])) if per_view else float("nan")
        for key in ("psnr", "ssim", "psnr_exposure_matched", "psnr_radiance", "ssim_radiance")
    } | {
        "views": len(per_view),
        "per_view": per_view,
    }
    if keep_images:
        out["images"] = images
    return out
