"""The SfM stage's picture: the recovered flight from above and from the side (``posed.h5``),
with the ground truth aligned onto it (Umeyama, scale included) when a ground-truth file is
given, and the ATE in the title. Drawn through the shared base :mod:`dronecap.plots`."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from dronecap.plots import pyplot, save_png


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
