"""Where a steady training step goes: each C++ kernel's time and the glue between them.

The default ``scene-sized`` model on lego 160 px RGB, resolved as ``dronecap train`` resolves it
(``train_speed.as_trained``), trained --warm steps at 1 thread; then, at 1 and 2 threads, every
call into the compiled kernels (``nerf.backend``'s modules, the Adam kernel included) and into
torch's fused Adam and its finiteness pass (where they run) is timed for --steps steps, as are
the step's four sections (ray drawing, marching and the pre-pass; the training pass; the
optimizer; the occupancy updates). A
section's time less its kernels' is its glue: Python and small torch ops, during which the
second thread only waits. The timers add ~1 us per call.

    .venv/bin/python benchmarks/step_split.py [--warm 1100] [--steps 256]

Writes benchmarks/results/step_split.md (with the load average: measure on an idle machine).
"""

from __future__ import annotations

import argparse
import os
import time
from collections import defaultdict
from pathlib import Path

import torch
from _runs import write_page
from snapshot import RESULTS
from train_speed import as_trained, lego

from dronecap.nerf import adam_step, backend, occupancy
from dronecap.nerf.config import preset
from dronecap.nerf.trainer import Trainer

KERNELS = ("hashgrid", "mlp", "march", "adam")
TORCH_OPS = ("_fused_adam_", "_amp_foreach_non_finite_check_and_unscale_")
# the step's sections: (name, object, attribute, the kernels inside)
SECTIONS = (
    ("rays, marching, pre-pass", "trainer", "_march_batch",
     ("march.draw", "march.ray_aabb", "march.march", "hashgrid.visible")),
    ("training pass", "trainer", "accumulate_gradients",
     ("mlp.forward", "mlp.backward", "hashgrid.backward", "march.composite",
      "march.composite_backward", "march.sh_encode")),
    ("optimizer", adam_step, "step",
     ("adam.all_finite", "adam.adam_step", *(f"torch.{op}" for op in TORCH_OPS))),
    ("occupancy updates", occupancy, "update", ("hashgrid.grid_refresh", "hashgrid.density")),
)  # fmt: skip


class _Timed:
    """A kernel module whose functions add their wall time to ``spent`` under
    ``prefix.name``."""

    def __init__(self, module, prefix: str, spent: dict[str, float]) -> None:
        self._module, self._prefix, self._spent = module, prefix, spent

    def __getattr__(self, name: str):
        fn = getattr(self._module, name)
        if not callable(fn):
            return fn
        return _timer(fn, f"{self._prefix}.{name}", self._spent)


def _timer(fn, name: str, spent: dict[str, float]):
    """``fn`` adding its wall time to ``spent[name]``."""

    def timed(*args, **kwargs):
        t0 = time.perf_counter()
        try:
            return fn(*args, **kwargs)
        finally:
            spent[name] += time.perf_counter() - t0

    return timed


def measure(tr: Trainer, threads: int, steps: int) -> tuple[dict, dict, float]:
    """Per-step ms of each kernel and section, and of the whole step, at ``threads``."""
    torch.set_num_threads(threads)
    tr.train(8)
    kernels: dict[str, float] = defaultdict(float)
    sections: dict[str, float] = defaultdict(float)
    saved = dict(backend._loaded)
    originals = []
    try:
        for name in KERNELS:
            backend._loaded[name] = _Timed(backend.load(name), name, kernels)
        adam = tr.adam  # the trainer holds its optimizer kernel from set-up
        tr.adam = None if adam is None else backend._loaded["adam"]
        for name in TORCH_OPS:
            originals.append((torch, name, getattr(torch, name)))
            setattr(torch, name, _timer(getattr(torch, name), f"torch.{name}", kernels))
        for label, owner, attr, _ in SECTIONS:
            obj = tr if owner == "trainer" else owner
            originals.append((obj, attr, getattr(obj, attr)))
            setattr(obj, attr, _timer(getattr(obj, attr), label, sections))
        t0 = time.perf_counter()
        tr.train(steps)
        total = time.perf_counter() - t0
    finally:
        tr.adam = adam
        backend._loaded.update(saved)
        for obj, attr, fn in reversed(originals):
            if obj is tr:
                delattr(tr, attr)  # back to the class's method
            else:
                setattr(obj, attr, fn)
    per = 1000.0 / steps
    return ({k: v * per for k, v in kernels.items()}, {k: v * per for k, v in sections.items()},
            total * per)  # fmt: skip


def table(rows: dict[int, tuple[dict, dict, float]]) -> list[str]:
    """Markdown rows: each section with its kernels and glue, then each kernel, per thread count."""
    threads = sorted(rows)
    head = "| part | " + " | ".join(f"{t} thread(s): ms / step" for t in threads) + " |"
    out = [head, "|---|" + "---:|" * len(threads)]
    out.append("| **whole step** | " + " | ".join(f"**{rows[t][2]:.2f}**" for t in threads) + " |")
    for label, _, _, inside in SECTIONS:
        cells = []
        for t in threads:
            kernels, sections, _ = rows[t]
            k = sum(kernels.get(name, 0.0) for name in inside)
            cells.append(f"{sections.get(label, 0.0):.2f} (kernels {k:.2f}, glue "
                         f"{sections.get(label, 0.0) - k:.2f})")  # fmt: skip
        out.append(f"| {label} | " + " | ".join(cells) + " |")
    names = sorted(rows[threads[0]][0], key=lambda n: -rows[threads[0]][0][n])
    for name in names:
        out.append(f"| kernel `{name}` | " + " | ".join(f"{rows[t][0].get(name, 0.0):.3f}"
                                                       for t in threads) + " |")  # fmt: skip
    return out


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--warm", type=int, default=1100, help="steps trained before timing")
    p.add_argument("--steps", type=int, default=256, help="steps timed per thread count")
    p.add_argument("--cache", default="/tmp/dronecap_bench")
    args = p.parse_args()
    torch.set_num_threads(1)
    ds = lego(Path(args.cache))
    tr = Trainer(as_trained(preset("scene-sized"), ds), ds)
    tr.train(args.warm)
    rows = {t: measure(tr, t, args.steps) for t in (1, 2)}
    load = " ".join(f"{x:.1f}" for x in os.getloadavg())
    lines = [
        "# Where a training step goes",
        "",
        f"lego 160 px RGB, default `scene-sized`, after {args.warm} steps; {args.steps} steps "
        f"timed per thread count; torch {torch.__version__}. Glue = a section's time less its "
        f"kernels' (Python and small torch ops). Load average (1/5/15 min) at the end: {load}.",
        f"Command: `.venv/bin/python benchmarks/step_split.py --warm {args.warm} --steps "
        f"{args.steps}`",
        "",
        *table(rows),
    ]
    write_page(lines, RESULTS / "step_split.md")


if __name__ == "__main__":
    main()
