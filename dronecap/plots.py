"""Pictures people look at, drawn from the files the stages wrote (never from their internals).

- :func:`training_curve`: test-free training signal of a run (``metrics.json`` history): PSNR
  and loss against the step and against the wall time;
- :func:`trajectory_plot`: the recovered flight from above and from the side (``posed.h5``),
  with the ground truth aligned onto it (Umeyama, scale included) when a ground-truth file is
  given, and the ATE in the title.

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


def trajectory_plot(
    posed_path: str | Path, out: str | Path, gt_path: str | Path | None = None
) -> Path | None:
    """Camera centres of ``posed.h5`` from above (x-y) and from the side (x-z) -> PNG.

    A swarm's drones are drawn in a colour each. With ``gt_path`` (the simulator's flight.json /
    poses.json), the ground-truth centres of the same source frames are aligned onto the
    recovered ones by a similarity (Umeyama) and drawn too; the title gives the ATE as a
    percentage of the flight's extent.
    """
    from dronecap.datasets.format import open_dataset

    ds = open_dataset(posed_path)
    if ds.poses is None or ds.n == 0:
        return None
    est = ds.poses[:, :3, 3]
    title = f"recovered flight: {ds.n} cameras"
    ref = None
    if gt_path is not None and ds.source_index is not None:
        from dronecap.sfm.align import load_ground_truth, umeyama

        gt = load_ground_truth(gt_path)
        have = [i for i, s in enumerate(ds.source_index) if int(s) in gt]
        if len(have) >= 3:
            g = np.stack([gt[int(ds.source_index[i])][:3, 3] for i in have])
            sim = umeyama(g, est[have])
            ref = sim.apply_points(g)
            err = np.linalg.norm(ref - est[have], axis=1)
            extent = float(np.linalg.norm(est.max(0) - est.min(0))) or 1.0
            title += f", ATE {100 * np.sqrt(np.mean(err**2)) / extent:.2f} % of the extent"
    plt = pyplot()
    if plt is None:
        return None
    fig, axes = plt.subplots(1, 2, figsize=(11, 4.5))
    for ax, (a, b), name in zip(axes, ((0, 1), (0, 2)), ("top (x-y)", "side (x-z)"), strict=True):
        if ref is not None:
            ax.plot(ref[:, a], ref[:, b], "-", color="0.6", lw=2, label="ground truth (aligned)")
        for d in np.unique(ds.drones()):  # a swarm: one colour per drone
            e, several = est[ds.drones() == d], len(ds.drone_names or []) > 1
            label = f"recovered: {ds.drone_name(int(d))}" if several else "recovered"
            ax.plot(e[:, a], e[:, b], ".-", color=f"C{d}", ms=3, lw=0.8, label=label)
        ax.plot(est[:1, a], est[:1, b], "o", color="C2", label="start")
        ax.set_title(name)
        ax.set_aspect("equal", adjustable="datalim")
        ax.grid(alpha=0.3)
        ax.set_xlabel("x (scene units)")
        ax.set_ylabel(("y", "z")[b - 1] + " (scene units)")
    axes[0].legend(fontsize=8)
    fig.suptitle(title)
    return save_png(fig, out)
