"""Trainer settings: one dataclass, and the named presets of the paper's Table II in one registry.

Every field is overridable from the CLI (``dronecap train --set field=value`` or the generated
``--field`` options) and from ``pipelines.yaml``. The GAP9 cost model reads the same dataclass.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any


@dataclass
class TrainConfig:
    """Tiny-DroNeRF / Instant-NGP training configuration (units in comments)."""

    # --- schedule -------------------------------------------------------------------------
    steps: int = 10_000  # optimizer steps
    images_per_step: int = 1  # training images rays are drawn from in one step (paper: 1)
    batch_samples: int = 8192  # B: samples (ray points) per optimizer step, after accumulation
    tile_samples: int = 1024  # samples per accumulation tile (GAP9 processes 1024 at a time)
    seed: int = 0
    # --- multiresolution hash encoding -------------------------------------------------------
    levels: int = 16  # L
    features: int = 2  # F per level
    log2_hashmap: int = 13  # log2(T), entries per level
    n_min: int = 16  # coarsest grid resolution (cells per axis)
    n_max: int = 2048  # finest grid resolution; ignored when auto_n_max
    auto_n_max: bool = False  # size n_max to the pixel footprint over the scene (see field.py)
    # --- MLPs -----------------------------------------------------------------------------
    hidden: int = 64  # width of both MLPs
    density_layers: int = 1  # hidden layers of the density MLP
    color_layers: int = 2  # hidden layers of the colour MLP
    geo_features: int = 16  # density MLP outputs (1 density + 15 geometry features)
    sh_degree: int = 4  # spherical-harmonics degree of the direction encoding (16 coefficients)
    # --- occupancy grid and ray marching ----------------------------------------------------
    grid_res: int = 128  # occupancy cells per axis over the AABB
    grid_decay: float = 0.95  # EMA decay of the cell densities
    grid_threshold: float = 0.01  # occupied if density > min(threshold, mean density)
    grid_warmup: int = 256  # steps during which every cell is updated every step
    grid_every: int = 16  # update interval after warm-up (paper's GAP9 run: 256)
    march_steps: int = 1024  # marching step = AABB diagonal / march_steps
    max_samples_per_ray: int = 1024
    # --- optimizer ------------------------------------------------------------------------
    lr: float = 1e-2
    betas: tuple[float, float] = (0.9, 0.99)
    eps: float = 1e-15
    weight_decay: float = 1e-6  # L2 on MLP weights only
    lr_schedule: str = "exp"  # "exp" (decay to lr_final_ratio) or "constant"
    lr_final_ratio: float = 0.03
    # --- numerics -------------------------------------------------------------------------
    precision: str = "fp32"  # "fp32", "fp16" or "bf16" storage of hash table and activations
    # --- data as the paper describes it (the trainer reads the real values from the dataset;
    #     the GAP9 cost model uses these when no dataset is given) -----------------------------
    resolution: int = 160  # image side in pixels
    train_images: int = 100  # images stored for training
    channels: int = 3  # 1 gray, 3 RGB

    def replace(self, **changes: Any) -> TrainConfig:
        """A copy with some fields changed (unknown names raise TypeError)."""
        return dataclasses.replace(self, **changes)


def _row(batch: int, log2_t: int) -> TrainConfig:
    """A Table II row of the 1-img/step, 160 px part of the sweep."""
    return TrainConfig(batch_samples=batch, log2_hashmap=log2_t)


PRESETS: dict[str, TrainConfig] = {
    # Table II, first row: Instant-NGP as published (100 img/step, 800 px, 2^18 samples, T=2^19).
    "instant-ngp": TrainConfig(
        images_per_step=100,
        batch_samples=1 << 18,
        tile_samples=1 << 18,
        log2_hashmap=19,
        resolution=800,
        steps=35_000,
    ),
    # The deployed configuration (bold row of Table II).
    "tiny-dronerf": _row(8192, 13),
    # The same hash table and MLPs (the same bytes exchanged in federated runs) sized to a
    # 160 px scene: the finest level at the pixel footprint (auto_n_max: 223 cells on lego, not
    # 2048), samples every diag/512 (not /1024: twice the rays per step at equal B) and a 64^3
    # occupancy grid (the 128^3 grid bought nothing at 160 px and costs 9 MB more on GAP9).
    # lego, 10k steps, all 200 test views, 3 seeds: 29.05 +- 0.06 dB vs 27.16 +- 0.07
    # (benchmarks/results/train_accuracy.md has the ablation).
    "tiny-dronerf-sized": _row(8192, 13).replace(auto_n_max=True, march_steps=512, grid_res=64),
    # A seconds-long configuration for the test suite.
    "test": TrainConfig(
        steps=60,
        batch_samples=2048,
        levels=8,
        log2_hashmap=12,
        n_max=256,
        grid_res=32,
        grid_warmup=16,
        grid_every=8,
        march_steps=256,
        hidden=32,
    ),
}
for _b, _bname in ((32768, "32k"), (16384, "16k"), (8192, "8k"), (4096, "4k")):
    for _t in (14, 13, 12, 11):
        PRESETS.setdefault(f"b{_bname}-t{_t}", _row(_b, _t))
# The bold row also answers to its Table II name.
TABLE2_ROWS: list[str] = ["instant-ngp"] + [
    f"b{b}-t{t}" for b in ("32k", "16k", "8k", "4k") for t in (14, 13, 12, 11)
]


def preset(name: str) -> TrainConfig:
    """A fresh copy of a named preset (KeyError lists the known names)."""
    if name not in PRESETS:
        raise KeyError(f"unknown preset {name!r}; known: {', '.join(sorted(PRESETS))}")
    return dataclasses.replace(PRESETS[name])


def parse_field(name: str, text: str) -> Any:
    """Parse ``text`` as the value of TrainConfig field ``name`` (ValueError when it cannot).

    Booleans take true/false/1/0/yes/no; ``betas`` takes "0.9,0.99".
    """
    fields = {f.name: f for f in dataclasses.fields(TrainConfig)}
    if name not in fields:
        raise ValueError(f"unknown setting {name!r}; known: {', '.join(sorted(fields))}")
    default = getattr(TrainConfig(), name)
    if isinstance(default, bool):
        low = text.strip().lower()
        if low not in ("true", "false", "1", "0", "yes", "no"):
            raise ValueError(f"{name} takes true or false, got {text!r}")
        return low in ("true", "1", "yes")
    if isinstance(default, tuple):
        parts = [float(p) for p in text.split(",")]
        if len(parts) != len(default):
            raise ValueError(f"{name} takes {len(default)} comma-separated numbers, got {text!r}")
        return tuple(parts)
    if isinstance(default, int):
        return int(float(text)) if "e" in text.lower() else int(text)
    return type(default)(text)


def add_config_arguments(parser: Any) -> None:
    """Add ``--preset``, ``--set k=v`` and one ``--field-name VALUE`` option per TrainConfig
    field to an argparse parser (options default to "not given")."""
    parser.add_argument(
        "--preset", default="tiny-dronerf", help=f"named configuration: {', '.join(PRESETS)}"
    )
    parser.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="FIELD=VALUE",
        help="override any configuration field (repeatable)",
    )
    group = parser.add_argument_group("configuration fields (override the preset)")
    for f in dataclasses.fields(TrainConfig):
        group.add_argument(
            "--" + f.name.replace("_", "-"),
            dest=f"cfg_{f.name}",
            default=None,
            metavar="V",
            help=f"{f.name} (preset value otherwise)",
        )


def config_from_args(args: Any) -> TrainConfig:
    """The TrainConfig that :func:`add_config_arguments` options describe (ValueError/KeyError
    on unknown presets, fields or unparsable values)."""
    cfg = preset(args.preset)
    changes: dict[str, Any] = {}
    for item in args.set:
        if "=" not in item:
            raise ValueError(f"--set takes FIELD=VALUE, got {item!r}")
        k, v = item.split("=", 1)
        changes[k.strip().replace("-", "_")] = parse_field(k.strip().replace("-", "_"), v)
    for f in dataclasses.fields(TrainConfig):
        text = getattr(args, f"cfg_{f.name}", None)
        if text is not None:
            changes[f.name] = parse_field(f.name, text)
    return cfg.replace(**changes)
