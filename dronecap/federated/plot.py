"""The PSNR-vs-step figure of federated runs (the paper's Figure: IID vs non-IID panels).

:func:`save_png` (from :mod:`dronecap.plots`) is re-exported for the benchmarks' figures.
"""

from __future__ import annotations

from pathlib import Path

from dronecap.plots import pyplot, save_png

SINGLE_COLOURS = ("tab:blue", "tab:orange", "tab:green", "tab:purple", "tab:brown", "tab:olive")


def plot_runs(panels: dict[str, dict], path: str | Path) -> Path | None:
    """One panel per run: global-model PSNR per round, and the baselines' curves.

    Args:
        panels: title -> a ``rounds.json`` document ({"rounds": [...], "baselines": {...}}).
        path: PNG to write (atomically).

    Returns:
        ``path``, or None when matplotlib is not installed (the figure skipped).
    """
    plt = pyplot()
    if plt is None:
        return None
    fig, axes = plt.subplots(1, len(panels), figsize=(5.5 * len(panels), 4), squeeze=False)
    for ax, (title, doc) in zip(axes[0], panels.items(), strict=True):
        rounds = doc.get("rounds", [])
        ax.plot(
            [r["steps"] for r in rounds],
            [r["psnr"] for r in rounds],
            "o-",
            color="black",
            lw=2,
            label="federated (global model)",
        )
        singles = iter(SINGLE_COLOURS)
        for name, curve in sorted(doc.get("baselines", {}).items()):
            central = name == "centralized"
            ax.plot(
                [c["steps"] for c in curve],
                [c["psnr"] for c in curve],
                "s--" if central else "o:",
                lw=1.5 if central else 1.0,
                color="tab:red" if central else next(singles, None),
                label=name.replace("_", " ") + (" (same steps)" if central else " alone"),
            )
        ax.set_title(title)
        ax.set_xlabel("optimizer steps (coordinator's critical path)")
        ax.set_ylabel("test PSNR [dB]")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    return save_png(fig, path)
