"""Resolve a training configuration against its dataset, once, into one object.

A :class:`TrainConfig` as the user gave it leaves some values to the data: ``n_max`` when
``auto_n_max`` (the scene-sized finest level), the channel count, the image size and the number
of training images. :func:`resolve` decides them from the dataset and returns a
:class:`Resolved`: the config with those values filled in (``config``; its ``n_max`` is the one
the model is built with), the scene the trainer takes from the dataset (bounds, near distance,
focal, background), the reason for each decided value, and the dataset's content hash.

The trainer, the checkpoint, ``run.json``, ``metrics.json``, ``cost.json`` and ``dronecap cost
RUN_DIR`` all read this one object, so the cost report models the network that was trained.
No torch here (the cost command reads run folders without it).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from dronecap.datasets.format import Dataset
from dronecap.errors import InputError

from .config import (
    DATA_DECIDED_FIELDS,
    LEGACY_VALUES,
    PHOTOMETRIC_FIELDS,
    SIZED_FIELDS,
    TrainConfig,
    config_from_dict,
    mlp_dtype,
    problems,
)
from .sizing import MemoryFn, SceneFacts, size_to_scene

AUTO_FAR_FIELD = "sh"  # the far field "auto" picks for footage without alpha


@dataclass(frozen=True, eq=False)
class Scene:
    """What the trainer takes from a dataset besides its pixels (all in scene units)."""

    aabb: np.ndarray  # float64 [2, 3]
    near: float  # mean near distance of the training views
    focal: float  # mean focal length (pixels)
    channels: int  # C
    background: tuple[float, ...]  # evaluation background, C values in [0, 1]

    def to_dict(self) -> dict[str, Any]:
        """JSON-able form (the AABB as nested lists)."""
        return dataclasses.asdict(self) | {"aabb": np.asarray(self.aabb, float).tolist()}

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> Scene:
        """Inverse of :meth:`to_dict` (also reads checkpoints written before resolving)."""
        return cls(
            np.asarray(d["aabb"], float),
            float(d["near"]),
            float(d["focal"]),
            int(d["channels"]),
            tuple(float(x) for x in d["background"]),
        )


def training_frames(ds: Dataset) -> np.ndarray:
    """Indices of the frames to train on: split 0 when the dataset has a split, else all.

    Raises:
        InputError: the dataset has a split but no frame in its train part (training on the
            test views and reporting them as test scores would be a wrong answer).
    """
    if ds.split is None:
        return np.arange(ds.n)
    idx = np.flatnonzero(ds.split == 0)
    if idx.size == 0:
        raise InputError(
            f"the dataset's split has no train frames (of {ds.n} frames: "
            f"{int(np.sum(ds.split == 1))} val, {int(np.sum(ds.split == 2))} test); "
            "re-run `dronecap split`"
        )
    return idx


def scene_of(ds: Dataset) -> Scene:
    """Bounds, near distance, focal, channels and background of ``ds`` (InputError when
    poses, intrinsics or the AABB are missing, or it has no train frames)."""
    if ds.poses is None or (ds.intrinsics is None and ds.cameras is None):
        raise InputError("dataset has no poses/intrinsics: run `dronecap sfm` first")
    if ds.aabb is None:
        raise InputError("dataset has no scene AABB (attrs 'aabb')")
    train = training_frames(ds)
    if ds.near_far is not None:
        near = float(np.mean(ds.near_far[train, 0]))
    else:
        centre = np.mean(ds.aabb, 0)
        near = float(np.mean(np.linalg.norm(ds.poses[train, :3, 3] - centre, axis=1)))
    bg = ds.background if ds.background is not None else (0.0,) * ds.channels
    focal = float(np.mean([0.5 * (k.fx + k.fy) for k in ds.cameras or [ds.intrinsics]]))
    return Scene(np.asarray(ds.aabb, float), near, focal, ds.channels, tuple(bg))


def auto_n_max(aabb: np.ndarray, near: float, focal: float) -> int:
    """Finest useful grid resolution: AABB extent over the pixel footprint at distance ``near``.

    Args:
        aabb: [2, 3] scene bounds (scene units).
        near: typical camera-to-surface distance (scene units), e.g. the mean near distance.
        focal: focal length in pixels.

    Returns:
        cells per axis (at least 16), the extent of the largest AABB side in pixel footprints.
    """
    extent = float(np.max(aabb[1] - aabb[0]))
    footprint = max(near, 1e-6) / focal
    return max(16, int(math.ceil(extent / footprint)))


@dataclass(frozen=True, eq=False)
class Resolved:
    """A configuration resolved against its dataset (see the module docstring).

    ``config`` holds every value the model is built and costed with: ``n_max`` (auto-sized
    when ``auto_n_max``), ``channels``, ``resolution`` (image width) and ``train_images``
    from the data, the MLP product dtype (``mlp_dtype``, "auto" decided for this CPU) and the
    photometric model (``learn_exposure``, ``learn_vignetting``: "on" or "off", "auto" decided
    for the dataset). ``reasons`` says why each of those has its value.
    """

    config: TrainConfig
    scene: Scene
    reasons: dict[str, str]
    dataset_sha256: str | None = None  # content hash of the dataset file (None: in memory)

    def to_dict(self) -> dict[str, Any]:
        """JSON-able form, as stored in run.json, metrics.json and the checkpoint."""
        return {
            "config": dataclasses.asdict(self.config),
            "scene": self.scene.to_dict(),
            "reasons": dict(self.reasons),
            "dataset_sha256": self.dataset_sha256,
        }

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> Resolved:
        """Inverse of :meth:`to_dict` (ValueError/KeyError/TypeError when malformed); fields
        a config was written without take the value it was trained with
        (:data:`nerf.config.LEGACY_VALUES`)."""
        return cls(
            config_from_dict(LEGACY_VALUES | d["config"]),
            Scene.from_dict(d["scene"]),
            {str(k): str(v) for k, v in d.get("reasons", {}).items()},
            d.get("dataset_sha256"),
        )


def choice_lines(resolved: Resolved, sized: bool) -> list[str]:
    """What was decided for the model and why, a line each (``dronecap train`` and ``federate``
    print them): with ``sized``, the channels and the sized fields; always the MLP products and
    the photometric model."""
    cfg, why = resolved.config, resolved.reasons
    fields = ("channels", *SIZED_FIELDS) if sized else ()
    lines = [f"sized: {k} = {getattr(cfg, k)}: {why.get(k, '')}" for k in fields]
    return lines + [
        f"{k} = {getattr(cfg, k)}: {why.get(k, '')}" for k in ("mlp_dtype", *DATA_DECIDED_FIELDS)
    ]


def check_config(cfg: TrainConfig) -> None:
    """Raise InputError listing every out-of-range field of ``cfg`` (nothing when fine)."""
    bad = problems(cfg)
    if bad:
        raise InputError("bad configuration: " + "; ".join(bad))


def resolve(
    cfg: TrainConfig,
    ds: Dataset,
    dataset_sha256: str | None = None,
    memory_fn: MemoryFn | None = None,
) -> Resolved:
    """Resolve ``cfg`` against ``ds`` (see the module docstring).

    A ``sized`` config is sized to the scene (:mod:`nerf.sizing`): n_max, marching step,
    occupancy grid and, when ``memory_fn`` (configuration -> modelled device bytes; the train
    command passes the GAP9 model's) is given, the table size within ``budget_mb``.

    Raises:
        InputError: an out-of-range field, a dataset the trainer cannot use (no poses,
            intrinsics or AABB; a split without train frames), or no sized model within the
            memory budget.
    """
    check_config(cfg)
    scene = scene_of(ds)
    h, w = ds.hw
    n_train = int(training_frames(ds).size)
    sized: dict[str, str] = {}
    if cfg.sized:
        data = cfg.replace(channels=ds.channels, resolution=w, train_images=n_train)
        cfg, sized = _size(data, scene, w, h, n_train, memory_fn)
    if cfg.auto_n_max:
        n_max = max(auto_n_max(scene.aabb, scene.near, scene.focal), cfg.n_min)
        why_n = (
            f"auto_n_max: largest AABB side {float(np.max(scene.aabb[1] - scene.aabb[0])):.3g} "
            f"over the pixel footprint at the mean near distance ({scene.near:.3g} / "
            f"focal {scene.focal:.1f} px)"
        )
    else:
        n_max, why_n = cfg.n_max, "set by the configuration"
    split = "the train split" if ds.split is not None else "all frames (the dataset has no split)"
    reasons = {
        "n_max": why_n,
        "channels": f"the dataset's images ({ds.channels} channel{'s' * (ds.channels > 1)})",
        "resolution": f"the dataset's image width ({w}x{h} px)",
        "train_images": f"frames in {split}",
    }
    reasons |= sized
    products = mlp_dtype(cfg)
    reasons["mlp_dtype"] = _why_mlp_dtype(cfg, products)
    alpha = ds.alpha is not None
    photometric = {k: _photometric(getattr(cfg, k), alpha) for k in PHOTOMETRIC_FIELDS}
    photometric["far_field"] = _far_field(cfg.far_field, alpha, ds.background is not None)
    reasons |= {k: why for k, (_, why) in photometric.items()}
    config = cfg.replace(
        n_max=n_max, channels=ds.channels, resolution=w, train_images=n_train, mlp_dtype=products
    ).replace(**{k: mode for k, (mode, _) in photometric.items()})
    return Resolved(config, scene, reasons, dataset_sha256)


def _photometric(mode: str, alpha: bool) -> tuple[str, str]:
    """("on" or "off", why) of a ``learn_exposure``/``learn_vignetting`` value ``mode`` for a
    dataset with (``alpha``) or without an alpha channel."""
    if mode != "auto":
        return mode, "set by the configuration"
    if alpha:
        return "off", "the dataset has an alpha channel (a synthetic composite: no camera to model)"
    return "on", "camera footage (no alpha channel): its exposure and lens shade the frames"


def _far_field(mode: str, alpha: bool, background: bool) -> tuple[str, str]:
    """(far field kind, why) of a ``far_field`` value ``mode`` for a dataset with
    (``alpha``) or without an alpha channel, that declares its ``background`` colour or not
    (:mod:`nerf.far_field`)."""
    if mode != "auto":
        return mode, "set by the configuration"
    if alpha:
        return "none", "the dataset has an alpha channel: its background is known (box only)"
    if background:
        return "none", "the dataset declares its background colour (box only)"
    return AUTO_FAR_FIELD, (
        "camera footage (no alpha channel): what lies past the box is learned per direction"
    )


def _why_mlp_dtype(cfg: TrainConfig, products: str) -> str:
    """Why the MLPs multiply in ``products`` (the resolved ``cfg.mlp_dtype``)."""
    if cfg.mlp_dtype != "auto":
        return "set by the configuration"
    if products == "bf16":
        return "this CPU has AMX-BF16 tiles: faster steps, more PSNR in a time budget"
    if cfg.precision == "fp16":
        return "fp16 storage (precision) is emulated with fp32 products"
    return "this CPU has no AMX-BF16 tiles (bf16 products would be slower than fp32)"


def _size(
    cfg: TrainConfig, scene: Scene, w: int, h: int, n_train: int, memory_fn: MemoryFn | None
) -> tuple[TrainConfig, dict[str, str]]:
    """``cfg`` sized to the scene and the reason of each sized field (InputError when no
    model fits the budget)."""
    facts = SceneFacts(
        tuple(float(e) for e in np.asarray(scene.aabb[1]) - np.asarray(scene.aabb[0])),
        scene.near, scene.focal, w, h, scene.channels, n_train,
    )  # fmt: skip
    keep = [k for k in cfg.sized_keep.split(",") if k]
    budget = cfg.budget_mb * 1e6 if memory_fn is not None else None
    try:
        sizing = size_to_scene(cfg, facts, memory_fn, budget, keep)
    except ValueError as err:
        raise InputError(f"{err} (raise budget_mb or set log2_hashmap)") from None
    return sizing.config, {c.field: c.reason for c in sizing.choices}


def legacy_resolved(config: dict[str, Any], scene: dict[str, Any]) -> Resolved:
    """The :class:`Resolved` of a checkpoint written before configs were resolved (its config
    and scene dicts): ``n_max`` re-derived from the scene exactly as the trainer of the time
    did; resolution and image count stay as the config had them (unknown then)."""
    cfg = config_from_dict(LEGACY_VALUES | config)
    sc = Scene.from_dict(scene)
    n_max = auto_n_max(sc.aabb, sc.near, sc.focal) if cfg.auto_n_max else cfg.n_max
    reasons = {"n_max": "re-derived from a checkpoint written before resolved configs"}
    return Resolved(cfg.replace(n_max=n_max, channels=sc.channels), sc, reasons, None)
