"""How sure the modelled GAP9 cost of a run to a target PSNR is: its steps and its trained share.

    .venv/bin/python benchmarks/gap9_to_target.py RUN/metrics.json [...] [--target 26.94]

`dronecap cost --search --runs ... --target-psnr DB` costs a run to its first held-out check at
or above DB, with the trained share averaged over all its steps. Both are bounds, not the
crossing: the checks are 1000 steps apart (the crossing lies between the last check below and
the first at or above; the linear interpolation between them is printed as an estimate), and
compaction keeps more samples in the first steps than later (the share over the steps to the
target is estimated from the run's history: the samples trained at every 100th step over the
run's mean marched samples per step). Each run is printed with: its run-average share, the
early share, no compaction (share 1, the run's hull) and neither compaction nor hull (how the
model before session 15 priced every run, then on its fixed schedule rule); variants that
coincide (a run without "samples") are printed once.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from dronecap.gap9.model import RunSamples, cost_report, deployed
from dronecap.nerf.config import config_from_dict


def crossing(curve: list[tuple[int, float]], target_db: float) -> tuple[int, int] | None:
    """(first check at or above ``target_db``, linear interpolation from the check before it)
    in steps; None when no check reached it."""
    for i, (step, psnr) in enumerate(curve):
        if psnr >= target_db:
            if i == 0:
                return step, step
            s0, p0 = curve[i - 1]
            return step, round(s0 + (target_db - p0) / (psnr - p0) * (step - s0))
    return None


def early_trained_fraction(doc: dict, steps: int) -> float | None:
    """Trained share over the first ``steps`` steps, from the history's per-step trained
    samples (every 100th step) over the run's mean marched samples per step; None without
    "samples" or history."""
    kept = [h["samples"] for h in doc.get("history") or [] if h["step"] <= steps]
    if not kept or not doc.get("samples") or not doc["samples"]["marched"]:
        return None
    marched_per_step = doc["samples"]["marched"] / doc["steps"]
    return min(sum(kept) / len(kept) / marched_per_step, 1.0)


def rows(path: Path, target_db: float) -> list[str]:
    """Markdown table rows of one run: steps x trained-share variants -> GAP9 min and J."""
    doc = json.loads(path.read_text())
    cfg = config_from_dict(doc["config"])
    run = RunSamples.from_metrics(doc)
    hit = crossing([(int(c["step"]), float(c["psnr"])) for c in doc.get("curve") or []], target_db)
    if hit is None:
        return [f"| {path.parent.name} | never reached {target_db:g} dB | | | | |"]
    first, interpolated = hit
    early = early_trained_fraction(doc, first)
    variants = [("run average", run)]
    if early is not None:
        variants.append(("over the steps to the target", RunSamples(early, run.hull_fraction)))
    variants += [("no compaction", RunSamples(1.0, run.hull_fraction)), ("neither", RunSamples())]
    seen = [r for _, r in variants]
    variants = [(k, r) for i, (k, r) in enumerate(variants) if r not in seen[:i]]
    out = []
    for steps, how in ((first, "first check"), (interpolated, "interpolated")):
        for label, r in variants:
            rep = cost_report(deployed(cfg.replace(steps=steps)), run=r)
            out.append(
                f"| {path.parent.name} | {steps} ({how}) | {label}: {r.trained_fraction:.2f} "
                f"| {r.hull_fraction:.3f} | {rep['latency']['train'] / 60:.1f} "
                f"| {rep['energy']['run']:.1f} |"
            )
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("metrics", nargs="+", type=Path, help="runs' metrics.json")
    ap.add_argument("--target", type=float, default=26.94, help="PSNR dB (default 26.94)")
    args = ap.parse_args()
    print("| run | steps to target | trained share | hull | GAP9 min | J |")
    print("|---|---|---|---:|---:|---:|")
    for path in args.metrics:
        print("\n".join(rows(path, args.target)))


if __name__ == "__main__":
    main()
