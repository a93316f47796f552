"""Trainer settings: one dataclass, and the named presets of the paper's Table II in one registry.

Every field is overridable from the CLI (``dronecap train --set field=value`` or the generated
``--field`` options; ``train`` leaves out :data:`DATA_FIELDS`, which its dataset decides) and
from ``pipelines.yaml``; :func:`apply_sets` is the one ``--set`` parser
(the GAP9 cost model's ``--set`` uses it too) and :func:`config_from_dict` the one way back from
JSON. :func:`problems` range-checks every field before any work starts. The trainer never uses
a config as given: :func:`dronecap.nerf.resolve.resolve` fills in what its dataset decides
(``n_max`` when auto-sized, channels, resolution, image count) and every consumer (trainer, run
folder, cost report) reads that resolved config.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Any

from dronecap.cpu import fast_bf16


@dataclass
class TrainConfig:
    """Tiny-DroNeRF / Instant-NGP training configuration (units in comments)."""

    # --- schedule -------------------------------------------------------------------------
    steps: int = 10_000  # optimizer steps
    images_per_step: int = 1  # training images rays are drawn from in one step (paper: 1)
    batch_samples: int = 8192  # B: samples (ray points) per optimizer step, after accumulation
    # what B counts: "trained" (the samples left after compaction, as Instant-NGP counts its
    # batch: a step marches more rays while compaction drops samples) or "marched" (session 15:
    # fewer samples trained as the scene gets opaque). lego 10k steps, 1 thread: 31.24 dB in
    # 358 s against 30.27 in 226 s; 60 s: +0.35 / +1.00 / +0.17 dB on lego / corridor / Himax
    # (docs/training.md "The batch counts", benchmarks/results/time_to_quality_compare.md)
    batch_counts: str = "trained"
    tile_samples: int = 1024  # samples per accumulation tile (GAP9 processes 1024 at a time)
    seed: int = 0
    # --- multiresolution hash encoding -------------------------------------------------------
    levels: int = 16  # L
    features: int = 2  # F per level
    log2_hashmap: int = 13  # log2(T), entries per level
    n_min: int = 16  # coarsest grid resolution (cells per axis)
    n_max: int = 2048  # finest grid resolution; replaced when resolved if auto_n_max
    auto_n_max: bool = False  # resolve n_max to the pixel footprint over the scene (resolve.py)
    sized: bool = False  # resolve n_max, march_steps, grid_res, log2_hashmap from the scene
    sized_keep: str = ""  # comma-separated fields the sizing keeps as given (set by the user)
    budget_mb: float = 21.0  # device memory (GAP9 model, MB) a sized model may use
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
    # the interval grows by one every grid_ramp steps until grid_every (Instant-NGP: 16)
    grid_ramp: int = 16
    grid_carve: bool = True  # alpha datasets: cells outside the views' silhouettes stay empty
    march_steps: int = 1024  # marching step = AABB diagonal / march_steps
    max_samples_per_ray: int = 1024
    # samples behind this transmittance are dropped before the training pass (nerf/compaction.py,
    # Instant-NGP's compaction; 0: every marched sample is trained on)
    train_min_transmittance: float = 1e-4
    # --- optimizer ------------------------------------------------------------------------
    lr: float = 1e-2
    betas: tuple[float, float] = (0.9, 0.99)
    eps: float = 1e-15
    weight_decay: float = 1e-6  # L2 on MLP weights only
    lr_schedule: str = "exp"  # "exp" (decay to lr_final_ratio) or "constant"
    lr_final_ratio: float = 0.03
    # --- numerics -------------------------------------------------------------------------
    precision: str = "fp32"  # "fp32", "fp16" or "bf16" storage of hash table and activations
    # MLP matrix products on the host: "fp32", "bf16" (inputs rounded to bf16, fp32 sums;
    # weights, gradients and Adam stay fp32) or "auto": bf16 on a CPU with AMX-BF16 tiles,
    # where the fused training kernel (nerf/mlp_kernel.py) multiplies on them, else fp32.
    # Resolved once. Default auto since session 24: the AMX products make the lego step 1.24x
    # faster at 1 thread, and 10-s runs (1 thread, paired seeds) gain +0.45 dB on lego (3
    # seeds), +0.27 on the corridor (6 seeds), +0.9 on real Himax test_23 (2 seeds)
    # (docs/training.md "bf16 products on AMX tiles").
    mlp_dtype: str = "auto"
    # --- the camera's photometric model, learned while training (nerf/photometric.py) -------
    # Per-frame exposure gains and one vignetting falloff multiply the rendered colour before
    # the loss; renders and evaluation show the scene without them. "on", "off", or "auto": on
    # unless the dataset has an alpha channel (a synthetic composite: nothing to compensate).
    # Resolved once (resolve.py). Default auto, measured (both on vs both off, 1 thread):
    # real Himax HM01B0 footage, 10k steps, test PSNR test_23 22.72 -> 23.88 dB, test_10
    # 22.43 -> 22.95; simulated corridor, 1500 steps, 2 seeds, PSNR against clean renders:
    # vignetting +1.7 dB, exposure drift +0.7/+1.1 dB, clean flight +0.11/-0.17 dB
    # (benchmarks/results/robustness_photometric_*.md).
    learn_exposure: str = "auto"  # a log-gain per training frame and channel, mean fixed at 0
    learn_vignetting: str = "auto"  # 1 + k1 r^2 + k2 r^4 + k3 r^6 about the principal point
    # lr of the photometric parameters over the model's lr: 2/3 keeps them at 0.01 under the
    # model's 0.015. 60 CPU s, 2 rounds, same run (results/time_to_quality_compare_photometric
    # _s18.md): object capture +0.57, AI-deck defects +0.17, corridor +0.06, Himax -0.05 dB
    # against ratio 1; lego (alpha: no photometric model) is unaffected.
    photometric_lr_ratio: float = 2 / 3
    # --- what a ray sees after it leaves the box (nerf/far_field.py) ------------------------
    # "none" (the fixed background), "sh" (16 SH coefficients per channel), "grid" (a 16 x 32
    # equirectangular map per channel) or "auto": none for images with alpha or a declared
    # background colour (known), the far field for footage without either. Resolved once.
    far_field: str = "auto"
    far_init: float = 0.5  # the far field's colour in every direction before training, (0, 1)
    # weight of the distortion loss (volrend.distortion, t in AABB diagonals) per ray: it
    # gathers each ray's weight into one stretch (a surface) instead of fog along the ray
    distortion: float = 0.0
    # --- data as the paper describes it (resolving against a dataset replaces them by the
    #     dataset's values; the GAP9 cost model uses these when no dataset is given) ------------
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
    # The default: the paper's MLPs and batch, n_max, marching step, occupancy grid and table
    # size resolved from the dataset within budget_mb (nerf/sizing.py), one tile per step on
    # the CPU (the same gradient as the GAP9's tiles of 1024). lego: see
    # benchmarks/results/scene_sized.md. The occupancy grid is updated as in Instant-NGP (every
    # 16 steps, decay 0.95): every 64 with 0.95^4 trained 12 % faster and gained 0.16 dB on lego
    # at 10k steps but lost 0.5-0.9 dB on the simulated corridor at 3k (3 seeds; see
    # benchmarks/results/time_to_quality.md, the *-every* runs). Learning rate 0.015 (the
    # paper's 0.01 until session 17; docs/training.md "The learning rate"): lego 10k steps 31.17
    # vs 31.07 dB; 60 s on one thread lego 28.15 vs 27.92, corridor 26.50 vs 26.21, Himax
    # test_23 24.85 vs 24.93 (time_to_quality_compare_lr_s17.md); modelled GAP9 minutes to
    # 26.94 dB, seeds 0 / 1 / 2: 9.8 / 8.8 / 10.0 vs 11.1 / 9.5 / 9.2 (gap9_curves_s17.md).
    # Rays from 100 random training frames per step (Instant-NGP's 100 images per step; the
    # paper's rows draw one frame's rays, a GAP9 memory choice) and a grid warm-up of one step
    # (the first update visits every cell, later ones a quarter uniformly plus a quarter of the
    # occupied ones: 76 full-hull updates took a third of a 10-s run). Session 21, lego, 1
    # thread: 10 s 21.60 -> 23.46 dB (3 seeds), 10k steps 31.19 -> 31.84 dB (grid_warmup 0),
    # docs/training.md "Rays from many frames". The grid's update interval grows by one every
    # 4 steps (reaching 16 at step 64; Instant-NGP's 16 reach it at step 256): 36 updates in
    # the first 256 steps instead of 76 (session 22, docs/training.md "fp32 products and fewer
    # early grid updates").
    "scene-sized": _row(8192, 13).replace(
        sized=True, tile_samples=8192, lr=0.015, images_per_step=100, grid_warmup=1, grid_ramp=4
    ),
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


DEFAULT_PRESET = "scene-sized"
SIZED_FIELDS = ("n_max", "march_steps", "grid_res", "log2_hashmap")  # what `sized` decides
DATA_FIELDS = ("resolution", "train_images", "channels")  # what resolving against data sets


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
        kind = f"{len(default)} comma-separated numbers"
    else:
        kind = "an integer" if isinstance(default, int) else "a number"
    try:
        if isinstance(default, tuple):
            parts = tuple(float(p) for p in text.split(","))
            if len(parts) == len(default):
                return parts
        elif isinstance(default, int):
            number = float(text)
            if number.is_integer():
                return int(number)
        elif isinstance(default, float):
            return float(text)
        else:
            return text.strip()
    except (ValueError, OverflowError):
        pass
    raise ValueError(f"{name} takes {kind}, got {text!r}")


def apply_sets(cfg: TrainConfig, assignments: list[str]) -> TrainConfig:
    """``cfg`` with ``FIELD=VALUE`` overrides applied (``--set``; dashes in names allowed).

    Raises ValueError naming the bad assignment (no '=', unknown field, unreadable value).
    """
    changes: dict[str, Any] = {}
    for item in assignments:
        if "=" not in item:
            raise ValueError(f"--set takes FIELD=VALUE, got {item!r}")
        key, text = item.split("=", 1)
        key = key.strip().replace("-", "_")
        changes[key] = parse_field(key, text.strip())
    return cfg.replace(**changes)


def config_from_dict(data: dict[str, Any]) -> TrainConfig:
    """The TrainConfig a JSON dict describes (``dataclasses.asdict`` of one, as written in
    run.json, metrics.json and checkpoints): missing fields take their defaults, keys that are
    not fields are ignored, lists become tuples. ValueError when a value has the wrong type."""
    fields = {f.name: f for f in dataclasses.fields(TrainConfig)}
    defaults = TrainConfig()
    clean: dict[str, Any] = {}
    for k, v in data.items():
        if k not in fields:
            continue
        want = getattr(defaults, k)
        if isinstance(want, tuple) and isinstance(v, list | tuple):
            v = tuple(float(x) for x in v)
        ok = (
            isinstance(v, bool)
            if isinstance(want, bool)
            else isinstance(v, type(want))
            and not isinstance(v, bool)
            or (isinstance(want, float) and isinstance(v, int) and not isinstance(v, bool))
        )
        if not ok:
            raise ValueError(f"config field {k} has {v!r}, expected a {type(want).__name__}")
        clean[k] = float(v) if isinstance(want, float) else v
    return TrainConfig(**clean)


def _finite(x: Any) -> bool:
    return isinstance(x, int | float) and not isinstance(x, bool) and math.isfinite(x)


# field -> (test, what it must be); tests take the value and the whole config
_RULES: dict[str, tuple[Any, str]] = {
    "steps": (lambda x, c: x >= 0, ">= 0"),
    "images_per_step": (lambda x, c: x >= 1, ">= 1"),
    "batch_samples": (lambda x, c: x >= 1, ">= 1"),
    "tile_samples": (lambda x, c: x >= 1, ">= 1"),
    "seed": (lambda x, c: x >= 0, ">= 0"),
    "levels": (lambda x, c: 1 <= x <= 64, "in 1..64"),
    "features": (lambda x, c: 1 <= x <= 64, "in 1..64"),
    "log2_hashmap": (lambda x, c: 1 <= x <= 26, "in 1..26"),
    "n_min": (lambda x, c: x >= 1, ">= 1"),
    "n_max": (lambda x, c: c.auto_n_max or x >= c.n_min, ">= n_min"),
    "hidden": (lambda x, c: x >= 1, ">= 1"),
    "density_layers": (lambda x, c: x >= 0, ">= 0"),
    "color_layers": (lambda x, c: x >= 0, ">= 0"),
    "geo_features": (lambda x, c: x >= 1, ">= 1 (the first one is the density)"),
    "sh_degree": (lambda x, c: 1 <= x <= 4, "in 1..4"),
    "grid_res": (lambda x, c: 1 <= x <= 1024, "in 1..1024"),
    "grid_decay": (lambda x, c: 0 < x <= 1, "in (0, 1]"),
    "grid_threshold": (lambda x, c: x >= 0, ">= 0"),
    "grid_warmup": (lambda x, c: x >= 0, ">= 0"),
    "grid_every": (lambda x, c: x >= 1, ">= 1"),
    "grid_ramp": (lambda x, c: x >= 1, ">= 1"),
    "march_steps": (lambda x, c: x >= 1, ">= 1"),
    "max_samples_per_ray": (lambda x, c: x >= 1, ">= 1"),
    "train_min_transmittance": (lambda x, c: 0 <= x < 1, "in [0, 1)"),
    "lr": (lambda x, c: x > 0, "> 0"),
    "eps": (lambda x, c: x > 0, "> 0"),
    "weight_decay": (lambda x, c: x >= 0, ">= 0"),
    "lr_final_ratio": (lambda x, c: x > 0, "> 0"),
    "photometric_lr_ratio": (lambda x, c: x > 0, "> 0"),
    "far_init": (lambda x, c: 0 < x < 1, "in (0, 1)"),
    "distortion": (lambda x, c: math.isfinite(x) and x >= 0, ">= 0"),
    "budget_mb": (lambda x, c: x > 0, "> 0"),
    "resolution": (lambda x, c: x >= 1, ">= 1"),
    "train_images": (lambda x, c: x >= 0, ">= 0"),
    "channels": (lambda x, c: x >= 1, ">= 1"),
}
LR_SCHEDULES = ("exp", "constant")
BATCH_COUNTS = ("trained", "marched")
PRECISIONS = ("fp32", "fp16", "bf16")
MLP_DTYPES = ("auto", "fp32", "bf16")
PHOTOMETRIC_MODES = ("auto", "on", "off")  # learn_exposure, learn_vignetting
PHOTOMETRIC_FIELDS = ("learn_exposure", "learn_vignetting")
FAR_FIELD_MODES = ("auto", "none", "sh", "grid")
FAR_SH_DEGREE = 4  # far_field "sh": bands 0..3, 16 coefficients per channel
FAR_GRID_ROWS, FAR_GRID_COLS = 16, 32  # far_field "grid": equirectangular logits per channel
# fields whose "auto" the dataset decides (resolve.py): a resumed model keeps its value
DATA_DECIDED_FIELDS = (*PHOTOMETRIC_FIELDS, "far_field")
# fields added after configs were first written: the value a config written without them was
# trained with (the resolved configs in run.json and checkpoints; see resolve.Resolved)
LEGACY_VALUES: dict[str, Any] = {
    "learn_exposure": "off",
    "learn_vignetting": "off",
    "grid_carve": False,
    "far_field": "none",
    "train_min_transmittance": 0.0,
    "batch_counts": "marched",
}


def problems(cfg: TrainConfig) -> list[str]:
    """What is wrong with ``cfg``, one line per field (empty when every field is in range):
    wrong types, NaN or infinite numbers, values out of range, unknown names."""
    out = []
    for f in dataclasses.fields(TrainConfig):
        v, want = getattr(cfg, f.name), getattr(TrainConfig(), f.name)
        if isinstance(want, bool):
            if not isinstance(v, bool):
                out.append(f"{f.name} must be true or false, got {v!r}")
        elif isinstance(want, int | float):
            if not _finite(v) or (isinstance(want, int) and not isinstance(v, int)):
                kind = "an integer" if isinstance(want, int) else "a finite number"
                out.append(f"{f.name} must be {kind}, got {v!r}")
            elif f.name in _RULES and not _RULES[f.name][0](v, cfg):
                out.append(f"{f.name} must be {_RULES[f.name][1]}, got {v!r}")
    if not (
        isinstance(cfg.betas, tuple)
        and len(cfg.betas) == 2
        and all(_finite(b) and 0 <= b < 1 for b in cfg.betas)
    ):
        out.append(f"betas must be two numbers in [0, 1), got {cfg.betas!r}")
    for name, allowed in (
        ("lr_schedule", LR_SCHEDULES),
        ("batch_counts", BATCH_COUNTS),
        ("precision", PRECISIONS),
    ):
        if getattr(cfg, name) not in allowed:
            out.append(f"{name} must be one of {', '.join(allowed)}, got {getattr(cfg, name)!r}")
    if cfg.mlp_dtype not in MLP_DTYPES:
        out.append(f"mlp_dtype must be one of {', '.join(MLP_DTYPES)}, got {cfg.mlp_dtype!r}")
    elif cfg.mlp_dtype == "bf16" and cfg.precision == "fp16":
        out.append("mlp_dtype bf16 cannot emulate fp16 activations (precision fp16): use fp32")
    for name in PHOTOMETRIC_FIELDS:
        if getattr(cfg, name) not in PHOTOMETRIC_MODES:
            modes = ", ".join(PHOTOMETRIC_MODES)
            out.append(f"{name} must be one of {modes}, got {getattr(cfg, name)!r}")
    if cfg.far_field not in FAR_FIELD_MODES:
        modes = ", ".join(FAR_FIELD_MODES)
        out.append(f"far_field must be one of {modes}, got {cfg.far_field!r}")
    return out


def mlp_dtype(cfg: TrainConfig) -> str:
    """The MLP product dtype ``cfg`` trains with: its ``mlp_dtype``, with "auto" decided here
    ("bf16" on a CPU with AMX-BF16 tiles unless ``precision`` is fp16, else "fp32")."""
    if cfg.mlp_dtype != "auto":
        return cfg.mlp_dtype
    return "bf16" if cfg.precision != "fp16" and fast_bf16() else "fp32"


def config_from_overrides(name: str, sets: list[str], fields: dict[str, Any]) -> TrainConfig:
    """Preset ``name`` with ``--set FIELD=VALUE`` assignments, then ``fields`` (values already
    parsed, e.g. from ``--steps 3000``) applied; with ``sized``, the sizing keeps the sized fields
    given here (ValueError/KeyError on unknown presets, fields or unparsable values; not
    range-checked: see :func:`problems`)."""
    cfg = apply_sets(preset(name), sets).replace(**fields)
    if cfg.sized:  # what the user set, the sizing keeps
        given = {item.split("=", 1)[0].strip().replace("-", "_") for item in sets} | set(fields)
        keep = [k for k in cfg.sized_keep.split(",") if k] + sorted(given & set(SIZED_FIELDS))
        cfg = cfg.replace(sized_keep=",".join(dict.fromkeys(keep)))
    return cfg
