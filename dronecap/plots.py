"""Pictures people look at, drawn from the files the stages wrote (never from their internals).

The shared plotting base, plus :func:`training_curve` (the test-free training signal of a run,
from ``metrics.json`` alone: PSNR and loss against the step and against the wall time). Stage
pictures that need a stage's own readers live in that stage's package (the SfM trajectory:
:mod:`dronecap.sfm.plots`), so this base imports no domain package.

matplotlib is optional (the ``plots`` extra). Every figure of the package gets it from
:func:`pyplot` (the Agg backend, imported on first use) and writes through :func:`save_png`;
without matplotlib a figure is skipped (its function returns None), the command still writes its
outputs, and :data:`SKIPPED` is printed once per process. The functions here return the PNG's
path, or None when the input holds nothing to draw or the figure was skipped.
"""

from __future__ import annotations

import functools
import json
import sys
from pathlib import Path
from typing import Any

import numpy as np

from dronecap.files import atomic_output

SKIPPED = "figures skipped: matplotlib is not installed (pip install 'dronecap[plots]')"


@functools.cache
def _say_skipped() -> None:
    """Print :data:`SKIPPED` to stderr (cached: once per process, however many figures)."""
    print(f"dronecap: {SKIPPED}", file=sys.stderr)


def pyplot() -> Any | None:
    """``matplotlib.pyplot`` on the file-only Agg backend, or None when matplotlib is not
    installed (then :data:`SKIPPED` is printed, once per process)."""
    try:
        import matplotlib
    except ModuleNotFoundError:
        _say_skipped()
        return None
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def save_png(fig: Any, path: str | Path, dpi: int = 110) -> Path:
    """Lay out ``fig`` (a matplotlib Figure), write it as a PNG atomically, close it.

    Args:
        fig: the figure, from :func:`pyplot`.
        path: the PNG to write.
        dpi: dots per inch (a 6.4 x 4.2 inch figure at 110 dpi is 704 x 462 px).
    """
    import matplotlib.pyplot as plt

    fig.tight_layout()
    with atomic_output(path) as tmp:
        fig.savefig(tmp, format="png", dpi=dpi, bbox_inches="tight")
    plt.close(fig)
    return Path(path)


def training_curve(metrics_path: str | Path, out: str | Path) -> Path | None:
    """PSNR and loss vs step and vs training seconds -> PNG.

    Reads a run's ``metrics.json``: ``history`` (rows {step, loss, psnr, seconds}, the PSNR
    estimated from the training loss), ``curve`` (held-out checks {step, seconds, psnr}, when
    the run made them) and the final test PSNR (a horizontal line).
    """
    try:
        m = json.loads(Path(metrics_path).read_text())
    except (OSError, json.JSONDecodeError):
        return None
    rows = [r for r in m.get("history", []) if isinstance(r, dict) and "step" in r]
    if not rows:
        return None
    step = np.array([r["step"] for r in rows], float)
    sec = np.array([r.get("seconds", np.nan) for r in rows], float)
    psnr = np.array([r.get("psnr", np.nan) for r in rows], float)
    loss = np.array([r.get("loss", np.nan) for r in rows], float)
    test = (m.get("test") or {}).get("psnr")
    curve = [c for c in m.get("curve") or [] if isinstance(c, dict) and "psnr" in c]
    plt = pyplot()
    if plt is None:
        return None
    fig, axes = plt.subplots(1, 3, figsize=(13, 3.6))
    for ax, x, label in ((axes[0], step, "step"), (axes[1], sec, "training time (s)")):
        ax.plot(x, psnr, lw=1, label="train (from loss)")
        if curve:
            key = "step" if label == "step" else "seconds"
            ax.plot([c[key] for c in curve], [c["psnr"] for c in curve], "o-", ms=3, lw=1,
                    color="C1", label="held-out views")  # fmt: skip
        if isinstance(test, float) and np.isfinite(test):
            ax.axhline(test, color="C3", ls="--", lw=1, label=f"test {test:.2f} dB")
        ax.set_xlabel(label)
        ax.set_ylabel("PSNR (dB)")
        ax.grid(alpha=0.3)
        ax.legend(loc="lower right", fontsize=8)
    axes[2].semilogy(step, loss, lw=1, color="C2")
    axes[2].set_xlabel("step")
    axes[2].set_ylabel("Huber loss")
    axes[2].grid(alpha=0.3)
    fig.suptitle(f"training curve: {Path(metrics_path).parent.name}")
    return save_png(fig, out)
