"""Which configurations fit a memory budget, and the memory-vs-PSNR Pareto plot of measured runs.

:func:`search` sweeps a grid of trainer settings and keeps those whose cost report fits the
budgets (the untiled footprint against the L3 budget, as the paper sizes its configurations
against 32 MB; the tiled L2 and L1 peaks against theirs). :func:`pareto_plot` draws memory
against PSNR for measured runs (or, without runs, the paper's Table II PSNRs, labelled as such)
and circles the chosen configuration: the smallest footprint within ``tolerance_db`` of the best
PSNR that fits. :func:`to_target` ranks the points by the modelled GAP9 energy (and time) their
runs spent to reach a target PSNR.
"""

from __future__ import annotations

import dataclasses
import itertools
import json
import math
from dataclasses import dataclass
from pathlib import Path

from dronecap.gap9.arch import DEFAULT_GRID_RULE, GridRule
from dronecap.gap9.model import RunSamples, cost_report, deployed
from dronecap.gap9.platform import Platform
from dronecap.nerf.config import LEGACY_VALUES, TrainConfig, config_from_dict, preset
from dronecap.plots import pyplot, save_png

# The sweep: batch B, log2(T), image side, occupancy grid side, MLP width, hash levels.
SEARCH_GRID: dict[str, tuple] = {
    "batch_samples": (4096, 8192, 16384, 32768),
    "log2_hashmap": (10, 11, 12, 13, 14, 15, 16),
    "resolution": (80, 160),
    "grid_res": (64, 128),
    "hidden": (32, 64),
    "levels": (8, 16),
}


@dataclass
class Budget:
    """Byte budgets: untiled footprint vs L3, tiled L2 peak, L1 need (None = not checked)."""

    l3: int | None = None
    l2: int | None = None
    l1: int | None = None

    def check(self, report: dict) -> bool:
        """True when the report's needs are within every given budget."""
        v = report["verdicts"]
        needs = (
            (self.l3, v["untiled_total_in_l3"]["need"]),
            (self.l2, v["l2"]["need"]),
            (self.l1, v["l1"]["need"]),
        )
        return all(b is None or need <= b for b, need in needs)


def search(
    budget: Budget,
    platform: Platform | None = None,
    base: TrainConfig | None = None,
    grid: dict[str, tuple] | None = None,
) -> list[dict]:
    """Every grid point (over ``base``, default tiny-dronerf) that fits, smallest footprint first.

    Returns dicts with the swept settings, ``mem_mb`` (untiled), ``l2_kb``, ``gop`` per step,
    ``train_min`` for the run's steps and ``config`` (the TrainConfig).
    """
    base = base or preset("tiny-dronerf")
    grid = grid or SEARCH_GRID
    keys = list(grid)
    out = []
    for values in itertools.product(*(grid[k] for k in keys)):
        cfg = dataclasses.replace(base, **dict(zip(keys, values, strict=True)))
        rep = cost_report(cfg, platform)
        if not budget.check(rep):
            continue
        out.append({
            **dict(zip(keys, values, strict=True)),
            "mem_mb": rep["memory"]["untiled"]["total"] / 1e6,
            "l2_kb": rep["memory"]["l2_peak"]["bytes"] / 1e3,
            "gop": rep["ops"]["step"]["total"] / 1e9,
            "train_min": rep["latency"]["train"] / 60,
            "config": cfg,
        })  # fmt: skip
    return sorted(out, key=lambda r: (r["mem_mb"], -r["batch_samples"]))


@dataclass
class Point:
    """One measured (or published) configuration on the Pareto plot.

    ``curve``: (step, held-out PSNR dB) pairs of the run's checks, in step order; ``psnr`` is
    the final test PSNR after ``cfg.steps`` steps; ``run``: what its steps worked on (its
    metrics' "samples"; the defaults for published rows and runs that predate them)."""

    label: str
    cfg: TrainConfig
    psnr: float
    mem_mb: float = 0.0
    fits: bool = True
    curve: list[tuple[int, float]] = dataclasses.field(default_factory=list)
    run: RunSamples = dataclasses.field(default_factory=RunSamples)

    def steps_to(self, target_db: float) -> int | None:
        """The first step at which the run reached ``target_db``: its first held-out check at
        or above it, else all its steps when the final test PSNR is; None when it never did."""
        for step, psnr in self.curve:
            if psnr >= target_db:
                return step
        return self.cfg.steps if self.psnr >= target_db else None


def load_runs(paths: list[str | Path]) -> list[Point]:
    """Points from ``metrics.json`` files with a "psnr" (top level, or under "test" as
    ``dronecap train`` writes it) and a "config" dict (a run's resolved configuration), and
    the run's "samples" when it recorded them (:meth:`RunSamples.from_metrics`).

    Raises ValueError naming a file that is unreadable or lacks those keys.
    """
    points = []
    for path in paths:
        p = Path(path)
        try:
            doc = json.loads(p.read_text())
            test = doc.get("test") or {}  # a trainer's metrics.json: scores under "test"
            psnr, cfg_d = float(doc["psnr"] if "psnr" in doc else test["psnr"]), doc["config"]
            run = RunSamples.from_metrics(doc)
        except (OSError, ValueError, KeyError, TypeError) as err:
            raise ValueError(f"{p}: not a metrics.json with 'psnr' and 'config' ({err})") from err
        if not math.isfinite(psnr) or not isinstance(cfg_d, dict):
            raise ValueError(f"{p}: 'psnr' must be a finite number and 'config' a dict")
        curve = [(int(c["step"]), float(c["psnr"])) for c in doc.get("curve") or []]
        label = p.parent.name or str(p)
        # a run's resolved configuration: fields it predates take the values it ran with
        cfg = config_from_dict(LEGACY_VALUES | cfg_d)
        points.append(Point(label, cfg, psnr, curve=curve, run=run))
    return points


def paper_points() -> list[Point]:
    """The paper's Table II PSNRs at the preset configurations (the 160 px rows)."""
    from dronecap.gap9.paper import TABLE2

    return [Point(name, preset(name), psnr) for name, (_, _, psnr) in TABLE2.items()]


def evaluate(points: list[Point], budget: Budget, platform: Platform | None = None) -> None:
    """Fill each point's modelled footprint (MB, untiled) and whether it fits ``budget``."""
    for pt in points:
        rep = cost_report(pt.cfg, platform)
        pt.mem_mb = rep["memory"]["untiled"]["total"] / 1e6
        pt.fits = budget.check(rep)


def to_target(
    points: list[Point],
    target_db: float,
    platform: Platform | None = None,
    grid_rule: GridRule = DEFAULT_GRID_RULE,
) -> list[dict]:
    """The modelled GAP9 cost of each point's run up to ``target_db``, cheapest energy first.

    Each point is costed in GAP9 tiles (:func:`deployed`) for the steps it took to reach the
    target (:meth:`Point.steps_to`), with its run's trained and hull fractions (averaged over
    all its steps) and its grid updated by ``grid_rule``; points that never reached it come
    last, with None.
    Returns dicts: label, steps, ``joules``, ``minutes`` (GAP9 training time), mem_mb,
    ``trained`` and ``hull`` (the run's fractions, :class:`RunSamples`).
    """
    rows = []
    for pt in points:
        steps = pt.steps_to(target_db)
        row = {"label": pt.label, "steps": steps, "mem_mb": pt.mem_mb, "joules": None,
               "minutes": None, "trained": pt.run.trained_fraction,
               "hull": pt.run.hull_fraction}  # fmt: skip
        if steps is not None:
            rep = cost_report(
                deployed(pt.cfg.replace(steps=steps)), platform, run=pt.run, grid_rule=grid_rule
            )
            row |= {"joules": rep["energy"]["run"], "minutes": rep["latency"]["train"] / 60}
        rows.append(row)
    return sorted(rows, key=lambda r: (r["joules"] is None, r["joules"] or 0.0))


def pareto_front(points: list[Point]) -> list[Point]:
    """Points no other point beats on both memory (lower) and PSNR (higher), by memory."""
    ordered = sorted(points, key=lambda q: (q.mem_mb, -q.psnr))
    front, best = [], float("-inf")
    for q in ordered:
        if q.psnr > best:
            front.append(q)
            best = q.psnr
    return front


def choose(points: list[Point], tolerance_db: float = 0.25) -> Point | None:
    """The smallest-footprint fitting point within ``tolerance_db`` of the best fitting PSNR."""
    fitting = [q for q in points if q.fits]
    if not fitting:
        return None
    best = max(q.psnr for q in fitting)
    return min((q for q in fitting if q.psnr >= best - tolerance_db), key=lambda q: q.mem_mb)


def _in_range(t: float, points: list[Point]) -> bool:
    """Whether tick ``t`` (MB) lies within the plotted memory range."""
    mems = [q.mem_mb for q in points]
    return min(mems) / 1.5 <= t <= max(mems) * 1.5


def pareto_plot(
    points: list[Point],
    chosen: Point | None,
    out: Path,
    budget_mb: float | None,
    title: str,
) -> Path | None:
    """Write the memory-vs-PSNR PNG: marker per batch size, log2(T) beside each point, the
    Pareto front, the L3 budget as a vertical line, the chosen point circled in red. Returns
    ``out``, or None when matplotlib is not installed (the figure skipped)."""
    plt = pyplot()
    if plt is None:
        return None
    markers = ["o", "s", "^", "D", "v", "P", "X", "*"]
    batches = sorted({q.cfg.batch_samples for q in points})
    fig, ax = plt.subplots(figsize=(6.4, 4.2))
    for i, b in enumerate(batches):
        sel = [q for q in points if q.cfg.batch_samples == b]
        ax.scatter(
            [q.mem_mb for q in sel], [q.psnr for q in sel], marker=markers[i % len(markers)],
            label=f"B = {b // 1024}k" if b % 1024 == 0 else f"B = {b}", zorder=3,
        )  # fmt: skip
        for q in sel:
            ax.annotate(str(q.cfg.log2_hashmap), (q.mem_mb, q.psnr), fontsize=7,
                        xytext=(3, 3), textcoords="offset points")  # fmt: skip
    front = pareto_front(points)
    ax.plot([q.mem_mb for q in front], [q.psnr for q in front], "k--", lw=0.8, label="Pareto front")
    if budget_mb is not None:
        ax.axvline(budget_mb, color="grey", lw=1, ls=":", label=f"L3 budget {budget_mb:g} MB")
    if chosen is not None:
        ax.scatter([chosen.mem_mb], [chosen.psnr], s=260, facecolors="none", edgecolors="red",
                   linewidths=1.8, zorder=4, label=f"chosen: {chosen.label}")  # fmt: skip
    ax.set_xscale("log")
    ticks = [t for t in (2, 5, 10, 20, 30, 50, 100, 200, 500, 1000) if _in_range(t, points)]
    ax.set_xticks(ticks, [f"{t:g}" for t in ticks])
    ax.xaxis.set_minor_formatter(plt.NullFormatter())
    ax.set_xlabel("memory, modelled untiled footprint [MB]")
    ax.set_ylabel("PSNR [dB]")
    ax.set_title(title, fontsize=9)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=7)
    return save_png(fig, out, dpi=120)
