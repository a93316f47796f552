"""A picture of a calibration: where the corners of the used views fall in the image (with the
3x3 regions the coverage warning checks) and the RMS reprojection error of every view."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from dronecap.calibration.calibrate import COVERAGE_GRID, Calibration, View
from dronecap.plots import pyplot, save_png


def plot_calibration(cal: Calibration, views: list[View], path: str | Path) -> Path | None:
    """Write a PNG: left, the corners of the used views over the image frame; right, the
    per-view RMS error (px) with the overall RMS as a line. Returns its path, None when
    matplotlib is not installed (the figure skipped, see :mod:`dronecap.plots`)."""
    plt = pyplot()
    if plt is None:
        return None
    w, h = cal.camera.width, cal.camera.height
    used = [v for v in views if v.name in cal.view_errors]
    fig, (ax, bx) = plt.subplots(1, 2, figsize=(11, 4.2), width_ratios=(1.2, 1))
    colors = plt.cm.viridis(np.linspace(0, 1, max(len(used), 1)))
    for v, c in zip(used, colors, strict=False):
        p = v.detection.image_points
        ax.plot(p[:, 0], p[:, 1], ".", ms=3, color=c)
    for i in range(1, COVERAGE_GRID):
        ax.axvline(w * i / COVERAGE_GRID, color="0.7", lw=0.8)
        ax.axhline(h * i / COVERAGE_GRID, color="0.7", lw=0.8)
    ax.set_xlim(0, w)
    ax.set_ylim(h, 0)
    ax.set_aspect("equal")
    ax.set_title(f"corners of {len(used)} views ({100 * cal.coverage:.0f}% of cells covered)")
    ax.set_xlabel("u (px)")
    ax.set_ylabel("v (px)")
    errs = [cal.view_errors[v.name] for v in used]
    bx.bar(range(len(errs)), errs, color=colors[: len(errs)])
    bx.axhline(cal.rms, color="k", ls="--", lw=1, label=f"overall RMS {cal.rms:.3f} px")
    bx.set_xticks(range(len(errs)), [Path(v.name).name for v in used], rotation=60, fontsize=7)
    bx.set_ylabel("RMS reprojection error (px)")
    bx.set_title("per-view error")
    bx.legend(loc="upper right")
    return save_png(fig, path)
