"""The Tiny-DroNeRF trainer: one training image per step, ~B packed samples, tile accumulation.

A step: update the occupancy grid when due, draw rays from ``images_per_step`` random training
images (as many as fit in B at the last step's samples per ray), march them through the grid,
drop the samples behind opaque surfaces (:mod:`nerf.compaction`), keep whole rays up to B
samples (``batch_counts``), render them tile by tile (tiles of
``tile_samples`` samples, gradients accumulated: the sum over tiles of ``loss_tile / R`` is the
full-batch loss), the camera's learned exposure and vignetting applied to the rendered colour
when on (:mod:`nerf.photometric`), Huber loss against the pixels composited on a random
background (images with alpha), one Adam step. With alpha masks the grid never marks a cell
outside the views' silhouettes (:mod:`nerf.carve`). Non-finite losses or gradients skip the
step; a run of them stops training with :class:`TrainingDiverged` before any weight becomes
non-finite.
"""

from __future__ import annotations

import dataclasses
import math
import time
from pathlib import Path

import numpy as np
import torch

from dronecap.camera import Camera
from dronecap.datasets.format import Dataset
from dronecap.errors import InputError

from . import adam_step, budget, carve, compaction, occupancy, train_pass
from .backend import kernel
from .batch import RayBatch, draw_rays, whole_rays
from .checkpoint import checkpoint_resolved, read_checkpoint, write_checkpoint
from .config import TrainConfig
from .field import DTYPES, Field
from .losses import psnr_from_mse
from .march_kernel import march_function
from .marching import Samples, tiles
from .photometric import Photometric
from .rays import frame_cameras, ray_aabb
from .render import Volume, render_view
from .resolve import Resolved, resolve, training_frames

MAX_BAD_STEPS = 20  # consecutive non-finite steps before training stops
PHOTOMETRIC_GROUP = 2  # index of the photometric parameters' Adam group (when it has any)


class TrainingDiverged(InputError):
    """Training kept producing non-finite losses; the last good weights were kept."""


class Trainer:
    """Trains a :class:`Field` on the training frames of a dataset (see module docstring).

    Args:
        cfg: the configuration (a preset with overrides), or one already resolved against
            ``train`` (:func:`nerf.resolve.resolve`); a plain config is resolved here.
        train: dataset holding the training frames (split 0, or all frames when it has no
            split); bounds, near distance, background and channel count come from it.
        device: torch device (CPU in this project).
        backend: kernel backend ("auto": the C++ kernels when they build; see nerf.backend).

    ``self.resolved`` is the one resolved configuration; ``self.cfg`` is its ``config`` (the
    values the model is built with, ``n_max`` included) and ``self.scene`` its scene.
    """

    def __init__(
        self,
        cfg: TrainConfig | Resolved,
        train: Dataset,
        device: str = "cpu",
        backend: str = "auto",
    ) -> None:
        resolved = cfg if isinstance(cfg, Resolved) else resolve(cfg, train)
        self._setup(resolved, device, backend)
        self.set_data(train)

    def _setup(self, resolved: Resolved, device: str, backend: str) -> None:
        cfg, scene = resolved.config, resolved.scene
        self.resolved, self.cfg, self.scene = resolved, cfg, scene
        self.lr_steps = cfg.steps  # the step count the lr decay runs to (see plan)
        self.device = torch.device(device)
        torch.manual_seed(cfg.seed)
        self.generator = torch.Generator(device=self.device).manual_seed(cfg.seed)
        self.field = Field(cfg, scene.channels, scene.aabb, backend).to(self.device)
        on = {"exposure": cfg.learn_exposure == "on", "vignetting": cfg.learn_vignetting == "on"}
        self.photometric = Photometric(cfg.train_images, scene.channels, **on).to(self.device)
        table = [self.field.encoding.table, *self.field.far_parameters()]  # no weight decay
        groups = [
            {"params": table, "weight_decay": 0.0},
            {"params": self.field.mlp_parameters(), "weight_decay": cfg.weight_decay},
        ]
        photometric = list(self.photometric.parameters())
        if photometric:  # its own group (PHOTOMETRIC_GROUP), no weight decay
            groups.append({"params": photometric, "weight_decay": 0.0})
        # fused: one kernel over all parameters, ~7x faster than the default multi-tensor Adam on
        # the ~0.5 M hash-table entries (0.7 vs 6.3 ms per step, 1 thread; same update)
        self.optimizer = torch.optim.Adam(
            groups, lr=cfg.lr, betas=tuple(cfg.betas), eps=cfg.eps, fused=True
        )
        self.aabb = torch.as_tensor(scene.aabb, dtype=torch.float32, device=self.device)
        diag = float(np.linalg.norm(scene.aabb[1] - scene.aabb[0]))
        self.step_size = diag / cfg.march_steps
        self.grid_cfg = occupancy.grid_config(cfg)
        self.grid = occupancy.init_state(self.grid_cfg, self.device)
        self.step, self.train_seconds = 0, 0.0
        self.tally = compaction.Tally()  # samples marched and trained on: the GAP9 model's input
        self.samples_per_ray = float(min(cfg.max_samples_per_ray, cfg.march_steps))
        self.images = None
        self.camera: Camera | None = None
        self.backend = backend
        self.march = march_function(backend)
        self.adam = kernel("adam", backend) if self.device.type == "cpu" else None
        self.field.prepare_kernels()  # kernels built before any step is timed

    def set_data(self, train: Dataset) -> None:
        """Use the training frames of ``train`` (same channels as the model) from now on."""
        if train.channels != self.scene.channels:
            raise InputError(
                f"dataset has {train.channels} channels, the model {self.scene.channels}"
            )
        if train.poses is None or (train.intrinsics is None and train.cameras is None):
            raise InputError("dataset has no poses/intrinsics: run `dronecap sfm` first")
        idx = training_frames(train)
        if idx.size == 0:
            raise InputError("dataset has no frames to train on")
        self.images = torch.as_tensor(train.images[idx], device=self.device)  # uint8 [N,H,W,C]
        self.alpha = (
            None if train.alpha is None else torch.as_tensor(train.alpha[idx], device=self.device)
        )
        self.poses = torch.as_tensor(train.poses[idx], dtype=torch.float32, device=self.device)
        self.cameras, self.camera_index = frame_cameras(train, idx, self.device)
        if self.cfg.grid_carve and self.alpha is not None:
            args = (self.aabb, self.alpha, self.poses, self.cameras, self.camera_index)
            self.grid = occupancy.restrict(self.grid, carve.hull(self.grid_cfg.res, *args))
        self.camera = self.cameras[0]
        if self.photometric.resize_frames(idx.size):  # other frames: their gains start at 1
            group = self.optimizer.param_groups[PHOTOMETRIC_GROUP]
            for p in group["params"]:
                self.optimizer.state.pop(p, None)
            group["params"] = list(self.photometric.parameters())

    # --- training ---------------------------------------------------------------------------
    def _lr(self, step: int) -> float:
        """The model's learning rate at ``step`` (the photometric group takes
        ``photometric_lr_ratio`` times it)."""
        return budget.learning_rate(self.cfg, step, self.lr_steps)

    def _draw_rays(self, n_rays: int) -> RayBatch:
        """Random pixels of ``images_per_step`` random training images: rays and targets."""
        return draw_rays(
            self.images, self.alpha, self.poses, self.cameras, self.camera_index,
            self.scene.background, self.cfg.images_per_step, n_rays, self.generator, self.backend,
        )  # fmt: skip

    def plan(self, steps: int) -> None:
        """Decay the learning rate over ``steps`` from now on (a time budget re-plans it); the
        configuration's ``steps`` stays what was asked until :meth:`finish`."""
        self.lr_steps = steps

    def adopt(self, resolved: Resolved) -> None:
        """Go on with ``resolved``: a resumed model's new step target, data-decided fields and
        MLP products (the caller checks nothing else changed and keeps the model's n_max)."""
        self.resolved, self.cfg, self.lr_steps = resolved, resolved.config, resolved.config.steps
        self.field.product_dtype = DTYPES[self.cfg.mlp_dtype]

    def finish(self, why: str) -> None:
        """Make the steps trained the configuration's ``steps`` (``why``: its reason), when a
        budget or an early stop ended training elsewhere than the steps asked: run.json,
        metrics.json, the checkpoint and the cost report then all give what ran."""
        if self.step != self.cfg.steps:
            r = self.resolved
            steps = r.config.replace(steps=self.step)
            self.adopt(Resolved(steps, r.scene, r.reasons | {"steps": why}, r.dataset_sha256))

    def _march_batch(self) -> tuple[RayBatch, Samples]:
        """Rays of one step and their samples (whole rays, with encodings when compacted): about
        B to train on, at most MARCH_CAP x B marched (``batch_counts`` "trained"), or at most B
        marched, less those compaction drops ("marched")."""
        cfg = self.cfg
        n_rays = int(min(max(cfg.batch_samples / self.samples_per_ray, 16), cfg.batch_samples))
        rays = self._draw_rays(n_rays)
        t_near, t_far, _ = ray_aabb(rays.origins, rays.dirs, self.aabb, self.backend)
        jitter = torch.rand(n_rays, generator=self.generator, device=self.device)
        s = self.march(
            rays.origins, rays.dirs, t_near, t_far, self.step_size, self.grid, self.aabb,
            cfg.max_samples_per_ray, jitter,
        )  # fmt: skip
        trained = cfg.batch_counts == "trained"  # else B counts the marched samples
        rays, s = whole_rays(rays, s, (compaction.MARCH_CAP if trained else 1) * cfg.batch_samples)
        thresh = cfg.train_min_transmittance
        rays, kept = self.tally.compact(self.step, rays, s, self.field, thresh, cfg.batch_samples)
        self.samples_per_ray = max((kept if trained else s).n / rays.origins.shape[0], 0.01)
        return rays, kept

    def accumulate_gradients(self, rays: RayBatch, s: Samples) -> float:
        """Forward/backward of a batch tile by tile, accumulating into ``.grad``.

        Tiles are runs of whole rays holding about ``tile_samples`` samples; each tile's
        loss is its Huber sum divided by the batch's ray count and channel count, so the
        accumulated gradient equals the full-batch one. The rendered colour passes through
        the photometric model (exposure, vignetting; the identity when both are off) before
        the loss. Returns the batch loss.
        """
        n_rays, total = rays.target.shape[0], 0.0
        for a, b, tile in tiles(s, self.cfg.tile_samples):
            part = rays.rows(a, b)
            total += train_pass.tile_loss(
                self.field, self.photometric, part, tile, n_rays, self.cfg.distortion, self.aabb
            )
        return total

    def updated_grid(self, grid: occupancy.GridState, step: int) -> occupancy.GridState:
        """``grid`` after one occupancy update at optimizer step ``step`` by this field (the
        fused C++ query and draws where they run)."""
        draws = kernel("march", self.backend) if self.device.type == "cpu" else None
        return occupancy.update(
            self.grid_cfg, grid, step, self.field.density, self.aabb, self.step_size,
            self.generator, self.field.grid_refresh, draws,
        )  # fmt: skip

    def train_step(self) -> dict:
        """One optimizer step; returns its log {step, loss, psnr, samples, rays, ms, lr,
        skipped}."""
        t0 = time.perf_counter()
        if occupancy.due(self.grid_cfg, self.step):
            self.grid = self.updated_grid(self.grid, self.step)
        lr = self._lr(self.step)
        for i, group in enumerate(self.optimizer.param_groups):
            group["lr"] = lr * (self.cfg.photometric_lr_ratio if i == PHOTOMETRIC_GROUP else 1.0)
        rays, s = self._march_batch()
        for group in self.optimizer.param_groups:  # None: the backward hands its gradients
            for p in group["params"]:  # over, no sums
                p.grad = None
        loss = self.accumulate_gradients(rays, s)
        ok = math.isfinite(loss) and adam_step.step(self.optimizer, self.adam)  # not with inf/NaN
        if ok:
            self.field.encoding.round_storage_()
            self._bad_steps = 0
        else:
            self._bad_steps = getattr(self, "_bad_steps", 0) + 1
            if self._bad_steps >= MAX_BAD_STEPS:
                raise TrainingDiverged(
                    f"training diverged: {self._bad_steps} consecutive non-finite losses at step "
                    f"{self.step}; weights of the last good step are kept (try a lower lr)"
                )
        self.step += 1
        ms = 1000 * (time.perf_counter() - t0)
        self.train_seconds += ms / 1000
        mse_est = float(loss) * 2 * 0.1 if ok else math.nan  # Huber ~ d^2/(2 delta) when small
        return {
            "step": self.step,
            "loss": loss,
            "psnr": psnr_from_mse(mse_est) if ok else math.nan,
            "samples": s.n,
            "rays": int(rays.target.shape[0]),
            "ms": ms,
            "lr": lr,
            "skipped": not ok,
        }

    def train(self, steps: int) -> list[dict]:
        """Run ``steps`` more optimizer steps, quietly; per-step logs (the bare loop of federated
        clients and tests; a run folder's, with budgets and checkpoints, is nerf.run_dir's)."""
        if self.images is None:
            raise InputError("trainer has no training data (pass `train=` to Trainer.load)")
        self.field.train()
        return [self.train_step() for _ in range(steps)]

    # ----------------------------------------------------------------------------------------
    # weights and state
    def model_weights(self) -> dict[str, np.ndarray]:
        """Hash table, MLP and far-field weights (float32 numpy), exactly what FedAvg averages:
        never the photometric model (a drone's own frames' exposures and its lens)."""
        return {
            k: v.detach().cpu().float().numpy().copy() for k, v in self.field.state_dict().items()
        }

    def load_model_weights(self, w: dict[str, np.ndarray]) -> None:
        """Load weights from :meth:`model_weights` (InputError on missing/odd shapes or NaN)."""
        own = self.field.state_dict()
        if set(w) != set(own):
            raise InputError(f"weights have keys {sorted(w)}, expected {sorted(own)}")
        for k, v in w.items():
            if tuple(np.shape(v)) != tuple(own[k].shape):
                raise InputError(
                    f"weight {k} has shape {np.shape(v)}, expected {tuple(own[k].shape)}"
                )
            if not np.all(np.isfinite(v)):
                raise InputError(f"weight {k} contains non-finite values")
        self.field.load_state_dict(
            {k: torch.as_tensor(np.asarray(v, np.float32)) for k, v in w.items()}
        )

    def grid_state(self) -> dict[str, np.ndarray]:
        """Occupancy grid: {"density": float32 [R^3] EMA, "occupied": bool [R^3]}."""
        return occupancy.to_numpy(self.grid)

    def load_grid_state(self, g: dict[str, np.ndarray]) -> None:
        """Load a grid from :meth:`grid_state` (same resolution)."""
        n = self.grid_cfg.res**3
        if np.size(g["density"]) != n or np.size(g["occupied"]) != n:
            raise InputError(f"occupancy grid has the wrong size (expected {n} cells)")
        self.grid = occupancy.restrict(occupancy.from_numpy(g, self.device), self.grid.allowed)

    def save(self, path: str | Path) -> None:
        """Write a full checkpoint atomically (resolved config and scene, weights, photometric
        model, Adam, grid, step, RNG, camera)."""
        for k, v in self._state().items():
            if not torch.isfinite(v).all():
                raise TrainingDiverged(f"refusing to save non-finite weights ({k})", path)
        write_checkpoint(
            path,
            {
                "resolved": self.resolved.to_dict(),
                "field": self.field.state_dict(),
                "photometric": self.photometric.state_dict(),
                "optimizer": self.optimizer.state_dict(),
                "grid": self.grid_state(),
                "step": self.step,
                "train_seconds": self.train_seconds,
                "samples": [self.tally.marched, self.tally.trained],
                "samples_per_ray": self.samples_per_ray,
                "rng": {"generator": self.generator.get_state(), "torch": torch.get_rng_state()},
                "intrinsics": None if self.camera is None else dataclasses.asdict(self.camera),
            },
        )

    @classmethod
    def load(
        cls,
        path: str | Path,
        train: Dataset | None = None,
        device: str = "cpu",
        backend: str = "auto",
    ) -> Trainer:
        """A trainer restored from :meth:`save` (``train`` is needed only to keep training).

        Checkpoints written before configs were resolved (a ``config`` and a ``scene`` instead
        of ``resolved``) load too. InputError when the file is unusable.
        """
        ck = read_checkpoint(path)
        resolved = checkpoint_resolved(ck, path)
        self = cls.__new__(cls)
        self._setup(resolved, device, backend)
        try:
            self.field.load_state_dict(ck["field"])
            self.photometric.load_state_dict(ck.get("photometric", {}))  # none before it existed
        except RuntimeError as err:
            first = str(err).strip().splitlines()[0]
            msg = f"checkpoint weights do not fit its configuration: {first}"
            raise InputError(msg, path) from None
        try:
            self.optimizer.load_state_dict(ck["optimizer"])
        except (ValueError, KeyError) as err:
            raise InputError(f"checkpoint optimizer state does not fit: {err}", path) from None
        self.load_grid_state(ck["grid"])
        self.step = int(ck["step"])
        self.train_seconds = float(ck["train_seconds"])
        self.tally.marched, self.tally.trained = ck.get("samples", (0, 0))  # none before
        self.samples_per_ray = float(ck["samples_per_ray"])
        self.generator.set_state(ck["rng"]["generator"])
        torch.set_rng_state(ck["rng"]["torch"])
        if ck.get("intrinsics"):
            d = dict(ck["intrinsics"])
            d["distortion"] = tuple(d.get("distortion", ()))
            self.camera = Camera(**d)
        if train is not None:
            self.set_data(train)
        return self

    def _state(self) -> dict[str, torch.Tensor]:
        """Every learned tensor by name: the field's and the photometric model's
        (``photometric.<name>``)."""
        own = {f"photometric.{k}": v for k, v in self.photometric.state_dict().items()}
        return self.field.state_dict() | own

    def weights_finite(self) -> bool:
        """True when every weight of the field and the photometric model is finite."""
        return all(bool(torch.isfinite(v).all()) for v in self._state().values())

    # ----------------------------------------------------------------------------------------
    # inference (nerf.render does the work)
    def volume(self) -> Volume:
        """The model as :mod:`nerf.render` takes it."""
        cfg = self.cfg
        return Volume(
            self.field, self.grid, self.aabb, self.step_size, cfg.max_samples_per_ray, self.march
        )

    def render(
        self, c2w: np.ndarray, camera: Camera, background=None, **thresholds: float
    ) -> np.ndarray:
        """Render one view through ``camera`` (lens model included) -> float32 [H, W, C];
        ``background`` defaults to the dataset's; ``thresholds`` as in
        :func:`nerf.render.render_rays`."""
        bg = self.scene.background if background is None else background
        return render_view(self.volume(), c2w, camera, tuple(bg), **thresholds)

    def evaluate(
        self, test: Dataset, views=None, progress: bool = False, keep_images: bool = False
    ) -> dict:
        """PSNR/SSIM (scikit-image, stored resolution) of test views against ground truth
        composited on the dataset background, each render as the camera recorded it
        (:func:`.evaluate.recorder`): {"psnr", "ssim", "psnr_radiance", "per_view": [...]}."""
        from .evaluate import evaluate_views, recorder

        bg, record = self.scene.background, recorder(self.photometric, test)
        return evaluate_views(self.render, test, bg, views, progress, keep_images, record)

    def evaluate_all(self, test: Dataset, progress: bool = False) -> dict:
        """:meth:`evaluate` on all test views, keeping the renders under "images"."""
        return self.evaluate(test, None, progress, keep_images=True)

    def sample_counts(self) -> dict[str, float]:
        """What the run's steps worked on (:meth:`.compaction.Tally.counts`)."""
        return self.tally.counts(self.grid.allowed)

    def parameter_count(self) -> int:
        """Trainable parameters (hash table + MLPs + far field)."""
        return self.field.parameter_count()
