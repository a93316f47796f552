"""Test-view metrics: PSNR and SSIM with scikit-image on the stored resolution."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from skimage.metrics import peak_signal_noise_ratio, structural_similarity

from dronecap.datasets.format import Dataset, Intrinsics
from dronecap.progress import progress_bar

RenderFn = Callable[[np.ndarray, Intrinsics], np.ndarray]  # (c2w, K) -> float32 [H, W, C]


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
) -> dict:
    """Render and score views of ``ds``.

    Args:
        render: (c2w [4, 4], intrinsics) -> float32 [H, W, C].
        ds: dataset with poses and intrinsics.
        background: colour the ground truth is composited on (and the renders use).
        views: frame indices (default: all test views, see :func:`test_views`).
        keep_images: also return the renders under "images".

    Returns:
        {"psnr": mean, "ssim": mean, "per_view": [{"index", "psnr", "ssim"}], "views": n}.
    """
    idx = test_views(ds) if views is None else np.asarray(views, np.int64)
    per_view, images = [], []
    for i in progress_bar(idx, desc="evaluate", unit="view", disable=not progress):
        pred = render(ds.poses[i], ds.intrinsics)
        p, s = image_metrics(pred, ground_truth(ds, int(i), background))
        per_view.append({"index": int(i), "psnr": p, "ssim": s})
        if keep_images:
            images.append(pred)
    out = {
        "psnr": float(np.mean([v["psnr"] for v in per_view])) if per_view else float("nan"),
        "ssim": float(np.mean([v["ssim"] for v in per_view])) if per_view else float("nan"),
        "views": len(per_view),
        "per_view": per_view,
    }
    if keep_images:
        out["images"] = images
    return out
