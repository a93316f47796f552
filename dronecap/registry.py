"""The registry of ``dronecap`` commands: one entry per stage with its help, the conventional
files it reads and writes in a workspace, its key figure and its pictures: a stage's face,
declared once and read by the CLI (:mod:`dronecap.cli`), the pipeline runner and its summary
(:mod:`dronecap.pipeline`) and ``report.html`` (:mod:`dronecap.report_html`).

Each entry names a module in :mod:`dronecap.commands` defining ``Settings`` (a dataclass of
:func:`dronecap.settings.setting` fields: the options, their help and defaults) and
``run(settings) -> int`` (the exit code). The CLI (:mod:`dronecap.cli`), the ``pipelines.yaml``
validation (:mod:`dronecap.pipeline_spec`) and the pipeline runner (:mod:`dronecap.pipeline`)
all start here. This module imports only light modules (their heavy imports are inside their
functions), so ``dronecap --help`` stays fast; a command's module is imported when it is used.
"""

from __future__ import annotations

import importlib
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from dronecap import figures, pictures
from dronecap import workspace as ws

Picture = Callable[[Path, dict[str, Any], Path], "Path | None"]  # (stage dir, params, out)


@dataclass(frozen=True)
class Stage:
    """One command: what it is, what it reads and writes, how a summary shows it (a pipeline
    uses it as :class:`dronecap.pipeline_spec.PipelineStage`s)."""

    name: str
    module: str  # dronecap.commands.<module>
    help: str
    inputs: tuple[str, ...] = ()  # conventional names read from the workspace by default
    outputs: tuple[str, ...] = ()  # conventional names written to the workspace by default
    folder: str | None = None  # the setting naming its output folder (a pipeline stage's own)
    extends: frozenset[str] = frozenset()  # parameters that only extend the previous output
    figure: Callable[[Path], str] | None = None  # its key figure, read from its outputs
    pictures: tuple[tuple[str, Picture], ...] = ()  # (file name, drawer) for report.html
    pipeline: bool = True  # may be a pipeline stage

    def load(self) -> tuple[type, Callable[[Any], int]]:
        """(its Settings class, its run function); imports the command module."""
        mod = importlib.import_module(f"dronecap.commands.{self.module}")
        return mod.Settings, mod.run


_STAGES = (
    Stage("simulate", "simulate", "render a synthetic nano-drone flight video with ground truth",
          outputs=(ws.FLIGHT_VIDEO, ws.FLIGHT_INFO)),
    Stage("ingest", "ingest",
          "flight video or drone capture folder (+ telemetry) -> 160x160 gray selected frames.h5",
          outputs=(ws.FRAMES,), figure=figures.ingest,
          pictures=(("kept_frames.png", pictures.kept_frames),)),
    Stage("calibrate", "calibrate", "calibrate a camera from images or a video of a board",
          outputs=(ws.CALIBRATION,)),
    Stage("sfm", "sfm",
          "recover camera poses with COLMAP (pycolmap), normalise and bound the scene -> posed.h5",
          inputs=(ws.FRAMES,), outputs=(ws.POSED, ws.SFM_DIR), folder="sfm_dir",
          figure=figures.sfm, pictures=(("trajectory.png", pictures.trajectory),)),
    Stage("split", "split",
          "train/test split of a posed flight (every k-th frame to test) -> dataset.h5",
          inputs=(ws.POSED,), outputs=(ws.DATASET,), figure=figures.dataset),
    Stage("shard", "shard",
          "IID or viewpoint-sector shards of a dataset's train images, one file per drone -> "
          "shards/", inputs=(ws.DATASET,), outputs=(ws.SHARDS,), figure=figures.shards),
    Stage("import-blender", "import_blender",
          "NeRF Synthetic 360 scene (transforms_*.json + RGBA PNGs) -> dataset.h5",
          outputs=(ws.DATASET,), figure=figures.dataset),
    Stage("import-transforms", "import_transforms",
          "instant-ngp / nerfstudio transforms.json dataset (folder or .json) -> dataset.h5",
          outputs=(ws.DATASET,), figure=figures.dataset),
    Stage("import-colmap", "import_colmap",
          "COLMAP sparse model (sparse/0) + images folder -> dataset.h5",
          outputs=(ws.DATASET,), figure=figures.dataset),
    Stage("export-transforms", "export_transforms",
          "dataset -> nerfstudio/instant-ngp transforms.json, PNG images, coloured PLY, COLMAP "
          "model", inputs=(ws.DATASET,), outputs=(ws.TRANSFORMS,)),
    Stage("train", "train", "train Tiny-DroNeRF on a dataset -> run dir (resumable), cost.json",
          inputs=(ws.DATASET,), outputs=(ws.TRAIN_RUN,), folder="out",
          extends=frozenset({"steps"}), figure=figures.train,
          pictures=(("curve.png", pictures.training_curve),
                    ("truth_render_error.png", pictures.truth_render_error),
                    ("flythrough.webp", pictures.flythrough))),
    Stage("render", "render", "render views (test poses or an orbit) of a trained run",
          inputs=(ws.TRAIN_RUN,), outputs=(f"{ws.TRAIN_RUN}/render",)),
    Stage("export-geometry", "export_geometry",
          "mesh (marching cubes) and coloured point cloud, as PLY, of a trained run",
          outputs=("RUN_DIR/geometry",)),
    Stage("eval", "eval",
          "score a trained run on a dataset's test views -> RUN_DIR/eval_<dataset>.json",
          inputs=(ws.TRAIN_RUN,), outputs=(f"{ws.TRAIN_RUN}/eval_<dataset>.json",)),
    Stage("cost", "cost", "GAP9 memory/compute/latency/energy report for a configuration",
          outputs=(ws.COST,)),
    Stage("federate", "federate", "FedAvg of Tiny-DroNeRF across drones on Flower",
          inputs=(ws.SHARDS,), outputs=(ws.FEDERATE_RUN,), folder="out",
          figure=figures.federate),
    Stage("run", "run", "run a pipeline from pipelines.yaml with caching", pipeline=False),
)  # fmt: skip
STAGES: dict[str, Stage] = {s.name: s for s in _STAGES}
