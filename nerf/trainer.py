"""The Tiny-DroNeRF trainer: one training image per step, ~B packed samples, tile accumulation.

A step: update the occupancy grid when due, draw rays from ``images_per_step`` random training
images (as many as the running samples-per-ray estimate says fit in B samples), march them
through the grid, keep whole rays up to B samples, render them tile by tile (tiles of
``tile_samples`` samples, gradients accumulated: the sum over tiles of ``loss_tile / R`` is the
full-batch loss), Huber loss against the pixels composited on a random background (images with
alpha), one Adam step. Non-finite losses or gradients skip the step; a run of them stops
training with :class:`TrainingDiverged` before any weight becomes non-finite.
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from dronecap.datasets.format import Dataset, Intrinsics
from dronecap.errors import InputError
from dronecap.progress import progress_bar

from . import occupancy
from .checkpoint import read_checkpoint, write_checkpoint
from .config import TrainConfig
from .field import Field, auto_n_max
from .losses import huber_sum, psnr_from_mse
from .marching import Samples, take_rays
from .marching import march as march_reference
from .rays import camera_rays, ray_aabb
from .volrend import accumulate, packed_weights, render_packed

MAX_BAD_STEPS = 20  # consecutive non-finite steps before training stops
RENDER_RAYS = 1 << 15  # rays per chunk when rendering a view
RENDER_ROUND = 16  # samples per ray evaluated per round when rendering
RENDER_FIELD_CHUNK = 1 << 14  # samples per field call when rendering (activations stay in cache)


class TrainingDiverged(InputError):
    """Training kept producing non-finite losses; the last good weights were kept."""


@dataclass
class Scene:
    """What the trainer takes from a dataset besides its pixels (all in scene units)."""

    aabb: np.ndarray  # float64 [2, 3]
    near: float  # mean near distance of the training views
    focal: float  # mean focal length (pixels)
    channels: int  # C
    background: tuple[float, ...]  # evaluation background, C values in [0, 1]

    @classmethod
    def from_dataset(cls, ds: Dataset) -> Scene:
        """Bounds, near distance, focal, channels and background of ``ds`` (InputError when
        poses, intrinsics or the AABB are missing)."""
        if ds.poses is None or ds.intrinsics is None:
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
        k = ds.intrinsics
        return cls(np.asarray(ds.aabb, float), near, 0.5 * (k.fx + k.fy), ds.channels, tuple(bg))


def training_frames(ds: Dataset) -> np.ndarray:
    """Indices of the frames to train on: the train split when there is one, else all."""
    if ds.split is not None and np.any(ds.split == 0):
        return np.flatnonzero(ds.split == 0)
    return np.arange(ds.n)


def select_march(backend: str):
    """The marching function: the C++ kernel unless ``backend == "torch"`` or it cannot be
    built (then the PyTorch reference, :func:`nerf.marching.march`)."""
    if backend == "torch":
        return march_reference
    try:
        from .march_kernel import load_extension, march

        load_extension()
        return march
    except Exception:  # no compiler: the reference gives the same samples, slower
        if backend == "cpp":
            raise
        return march_reference


class Trainer:
    """Trains a :class:`Field` on the training frames of a dataset (see module docstring).

    Args:
        cfg: the configuration (a preset with overrides).
        train: dataset holding the training frames (frames of split 0, or all when no split
            marks any); AABB, near distance, background and channel count come from it.
        device: torch device (CPU in this project).
        backend: hash-grid backend ("auto": the C++ kernel when it builds).
    """

    def __init__(
        self, cfg: TrainConfig, train: Dataset, device: str = "cpu", backend: str = "auto"
    ) -> None:
        self._setup(cfg, Scene.from_dataset(train), device, backend)
        self.set_data(train)

    def _setup(self, cfg: TrainConfig, scene: Scene, device: str, backend: str) -> None:
        self.cfg = cfg
        self.scene = scene
        self.device = torch.device(device)
        torch.manual_seed(cfg.seed)
        self.generator = torch.Generator(device=self.device).manual_seed(cfg.seed)
        self.n_max = (
            auto_n_max(scene.aabb, scene.near, scene.focal) if cfg.auto_n_max else cfg.n_max
        )
        self.field = Field(cfg, scene.channels, scene.aabb, self.n_max, backend).to(self.device)
        table = [self.field.encoding.table]
        self.optimizer = torch.optim.Adam(
            [
                {"params": table, "weight_decay": 0.0},
                {"params": self.field.mlp_parameters(), "weight_decay": cfg.weight_decay},
            ],
            lr=cfg.lr,
            betas=tuple(cfg.betas),
            eps=cfg.eps,
        )
        self.aabb = torch.as_tensor(scene.aabb, dtype=torch.float32, device=self.device)
        diag = float(np.linalg.norm(scene.aabb[1] - scene.aabb[0]))
        self.step_size = diag / cfg.march_steps
        self.grid_cfg = occupancy.GridConfig(
            cfg.grid_res, cfg.grid_decay, cfg.grid_threshold, cfg.grid_warmup, cfg.grid_every
        )
        self.grid = occupancy.init_state(self.grid_cfg, self.device)
        self.step = 0
        self.train_seconds = 0.0
        self.samples_per_ray = float(min(cfg.max_samples_per_ray, cfg.march_steps))
        self.images = None
        self.march = select_march(backend)

    def set_data(self, train: Dataset) -> None:
        """Use the training frames of ``train`` (same channels as the model) from now on."""
        if train.channels != self.scene.channels:
            raise InputError(
                f"dataset has {train.channels} channels, the model {self.scene.channels}"
            )
        idx = training_frames(train)
        if idx.size == 0:
            raise InputError("dataset has no frames to train on")
        self.images = torch.as_tensor(train.images[idx], device=self.device)  # uint8 [N,H,W,C]
        self.alpha = (
            None if train.alpha is None else torch.as_tensor(train.alpha[idx], device=self.device)
        )
        self.poses = torch.as_tensor(train.poses[idx], dtype=torch.float32, device=self.device)
        self.intrinsics = train.intrinsics

    # ----------------------------------------------------------------------------------------
    # training
    def _lr(self, step: int) -> float:
        cfg = self.cfg
        if cfg.lr_schedule == "constant":
            return cfg.lr
        if cfg.lr_schedule == "exp":
            return cfg.lr * cfg.lr_final_ratio ** min(step / max(cfg.steps, 1), 1.0)
        raise InputError(f"unknown lr_schedule {cfg.lr_schedule!r}: use 'exp' or 'constant'")

    def _draw_rays(self, n_rays: int):
        """Random pixels of ``images_per_step`` random training images: rays and targets."""
        g, dev = self.generator, self.device
        n_img, h, w, c = self.images.shape
        k = self.intrinsics
        imgs = torch.randint(
            n_img, (min(self.cfg.images_per_step, n_img),), generator=g, device=dev
        )
        which = imgs[torch.randint(imgs.numel(), (n_rays,), generator=g, device=dev)]
        u = torch.randint(w, (n_rays,), generator=g, device=dev)
        v = torch.randint(h, (n_rays,), generator=g, device=dev)
        origins, dirs = camera_rays(self.poses[which], k.fx, k.fy, k.cx, k.cy, u, v)
        rgb = self.images[which, v, u].float() / 255.0
        if self.alpha is not None:
            a = (self.alpha[which, v, u].float() / 255.0).unsqueeze(-1)
            bg = torch.rand((n_rays, c), generator=g, device=dev)
            target = rgb * a + bg * (1.0 - a)
        else:
            bg = torch.as_tensor(self.scene.background, dtype=torch.float32, device=dev)
            bg = bg.expand(n_rays, c)
            target = rgb
        return origins, dirs, target, bg

    def _march_batch(self):
        """Rays of one step and their samples, cut to at most B samples (whole rays)."""
        cfg = self.cfg
        n_rays = int(
            np.clip(cfg.batch_samples / max(self.samples_per_ray, 1e-3), 16, cfg.batch_samples)
        )
        origins, dirs, target, bg = self._draw_rays(n_rays)
        t_near, t_far, _ = ray_aabb(origins, dirs, self.aabb)
        jitter = torch.rand(n_rays, generator=self.generator, device=self.device)
        s = self.march(
            origins,
            dirs,
            t_near,
            t_far,
            self.step_size,
            self.grid,
            self.aabb,
            cfg.max_samples_per_ray,
            jitter,
        )
        self.samples_per_ray = max(s.n / n_rays, 0.01)
        cum = torch.cumsum(s.counts, 0)
        keep = int(torch.searchsorted(cum, torch.tensor(cfg.batch_samples), right=True))
        keep = max(keep, 1)
        if keep < n_rays:
            s = take_rays(s, torch.arange(keep, device=self.device))
            origins, dirs, target, bg = origins[:keep], dirs[:keep], target[:keep], bg[:keep]
        return origins, dirs, target, bg, s

    def _render_rays(self, origins, dirs, s: Samples, bg):
        """Colour [R, C] of rays through the field (with autograd)."""
        field = self.field

        def color_sigma(t0, t1, ri):
            pts = origins[ri] + dirs[ri] * (0.5 * (t0 + t1)).unsqueeze(-1)
            return field(pts, dirs[ri])

        color, _, _ = render_packed(
            s.t_starts, s.t_ends, s.ray_indices, origins.shape[0], color_sigma, bg
        )
        return color

    def accumulate_gradients(self, origins, dirs, target, bg, s: Samples) -> float:
        """Forward/backward of a batch tile by tile, accumulating into ``.grad``.

        Tiles are runs of whole rays holding about ``tile_samples`` samples; each tile's
        loss is its Huber sum divided by the batch's ray count and channel count, so the
        accumulated gradient equals the full-batch one. Returns the batch loss.
        """
        n_rays, c = target.shape
        start = torch.cumsum(s.counts, 0) - s.counts
        tile_of_ray = torch.div(start, max(self.cfg.tile_samples, 1), rounding_mode="floor")
        bounds = torch.searchsorted(tile_of_ray, torch.unique(tile_of_ray)).tolist() + [n_rays]
        sample_bounds = (torch.cumsum(s.counts, 0) - s.counts).tolist() + [s.n]
        total = 0.0
        for a, b in zip(bounds[:-1], bounds[1:], strict=True):
            sa, sb = sample_bounds[a], sample_bounds[b]
            tile = Samples(
                s.ray_indices[sa:sb] - a, s.t_starts[sa:sb], s.t_ends[sa:sb], s.counts[a:b]
            )
            color = self._render_rays(origins[a:b], dirs[a:b], tile, bg[a:b])
            loss = huber_sum(color, target[a:b]) / (n_rays * c)
            loss.backward()
            total += float(loss.detach())
        return total

    def _grads_finite(self) -> bool:
        grads = [p.grad for p in self.field.parameters() if p.grad is not None]
        return bool(torch.isfinite(torch.stack([g.sum() for g in grads]).sum()))

    def train_step(self) -> dict:
        """One optimizer step; returns its log {step, loss, psnr, samples, rays, ms, lr,
        skipped}."""
        t0 = time.perf_counter()
        if occupancy.due(self.grid_cfg, self.step):
            self.grid = occupancy.update(
                self.grid_cfg,
                self.grid,
                self.step,
                self.field.density,
                self.aabb,
                self.step_size,
                self.generator,
            )
        lr = self._lr(self.step)
        for group in self.optimizer.param_groups:
            group["lr"] = lr
        origins, dirs, target, bg, s = self._march_batch()
        self.optimizer.zero_grad(set_to_none=False)
        loss = self.accumulate_gradients(origins, dirs, target, bg, s)
        ok = math.isfinite(loss) and self._grads_finite()
        if ok:
            self.optimizer.step()
            self.field.encoding.round_storage_()
            self._bad_steps = 0
        else:
            self._bad_steps = getattr(self, "_bad_steps", 0) + 1
            if self._bad_steps >= MAX_BAD_STEPS:
                raise TrainingDiverged(
                    f"training diverged: {self._bad_steps} consecutive non-finite losses at step "
                    f"{self.step}; weights of the last good step are kept (try a lower --lr)"
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
            "rays": int(target.shape[0]),
            "ms": ms,
            "lr": lr,
            "skipped": not ok,
        }

    def train(self, steps: int, progress: bool = True) -> list[dict]:
        """Run ``steps`` more optimizer steps from ``self.step``; per-step logs."""
        if self.images is None:
            raise InputError("trainer has no training data (pass `train=` to Trainer.load)")
        self.field.train()
        logs = []
        bar = progress_bar(
            range(steps),
            desc="train",
            unit="step",
            disable=not progress,
            initial=0,
            dynamic_ncols=True,
        )
        for _ in bar:
            log = self.train_step()
            logs.append(log)
            if progress and (self.step % 10 == 0):
                bar.set_postfix(
                    step=self.step,
                    loss=f"{log['loss']:.4f}",
                    psnr=f"{log['psnr']:.1f}",
                    spr=f"{log['samples'] / max(log['rays'], 1):.1f}",
                    ms=f"{log['ms']:.0f}",
                )
        return logs

    # ----------------------------------------------------------------------------------------
    # weights and state
    def model_weights(self) -> dict[str, np.ndarray]:
        """Hash table and MLP weights (float32 numpy), exactly what FedAvg averages."""
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
        self.grid = occupancy.from_numpy(g, self.device)

    def save(self, path: str | Path) -> None:
        """Write a full checkpoint atomically (config, scene, weights, Adam, grid, step, RNG)."""
        for k, v in self.field.state_dict().items():
            if not torch.isfinite(v).all():
                raise TrainingDiverged(f"refusing to save non-finite weights ({k})", path)
        write_checkpoint(
            path,
            {
                "config": dataclasses.asdict(self.cfg),
                "scene": dataclasses.asdict(self.scene),
                "field": self.field.state_dict(),
                "optimizer": self.optimizer.state_dict(),
                "grid": self.grid_state(),
                "step": self.step,
                "train_seconds": self.train_seconds,
                "samples_per_ray": self.samples_per_ray,
                "rng": {"generator": self.generator.get_state(), "torch": torch.get_rng_state()},
                "intrinsics": None
                if self.intrinsics is None
                else dataclasses.asdict(self.intrinsics),
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
        """A trainer restored from :meth:`save` (``train`` is needed only to keep training)."""
        ck = read_checkpoint(path)
        cfg_d = dict(ck["config"])
        cfg_d["betas"] = tuple(cfg_d["betas"])
        scene_d = dict(ck["scene"])
        scene_d["aabb"] = np.asarray(scene_d["aabb"])
        scene_d["background"] = tuple(scene_d["background"])
        self = cls.__new__(cls)
        self._setup(TrainConfig(**cfg_d), Scene(**scene_d), device, backend)
        self.field.load_state_dict(ck["field"])
        self.optimizer.load_state_dict(ck["optimizer"])
        self.load_grid_state(ck["grid"])
        self.step = int(ck["step"])
        self.train_seconds = float(ck["train_seconds"])
        self.samples_per_ray = float(ck["samples_per_ray"])
        self.generator.set_state(ck["rng"]["generator"])
        torch.set_rng_state(ck["rng"]["torch"])
        if ck.get("intrinsics"):
            d = dict(ck["intrinsics"])
            d["distortion"] = tuple(d.get("distortion", ()))
            self.intrinsics = Intrinsics(**d)
        if train is not None:
            self.set_data(train)
        return self

    # ----------------------------------------------------------------------------------------
    # inference
    @torch.no_grad()
    def render(self, c2w: np.ndarray, intrinsics: Intrinsics, background=None) -> np.ndarray:
        """Render one view.

        Args:
            c2w: [4, 4] camera-to-world (OpenCV axes).
            intrinsics: pinhole intrinsics; the output has its width and height.
            background: C values in [0, 1]; default the dataset's background.

        Returns:
            float32 [H, W, C] in [0, 1].
        """
        self.field.eval()
        h, w, k = intrinsics.height, intrinsics.width, intrinsics
        bg = torch.as_tensor(
            self.scene.background if background is None else background,
            dtype=torch.float32,
            device=self.device,
        )
        vv, uu = torch.meshgrid(
            torch.arange(h, device=self.device), torch.arange(w, device=self.device), indexing="ij"
        )
        pose = torch.as_tensor(np.asarray(c2w), dtype=torch.float32, device=self.device)
        out = []
        for a in range(0, h * w, RENDER_RAYS):
            u, v = uu.reshape(-1)[a : a + RENDER_RAYS], vv.reshape(-1)[a : a + RENDER_RAYS]
            origins, dirs = camera_rays(pose, k.fx, k.fy, k.cx, k.cy, u, v)
            out.append(self.render_rays(origins, dirs, bg))
        return torch.cat(out).reshape(h, w, -1).cpu().numpy().astype(np.float32)

    @torch.no_grad()
    def render_rays(
        self, origins, dirs, background, min_transmittance: float = 1e-3, min_weight: float = 1e-4
    ):
        """Colours [R, C] of rays [R, 3] (no grad), marching and evaluating ``RENDER_ROUND``
        samples per ray per round and stopping rays whose transmittance fell below
        ``min_transmittance`` (early termination: what lies behind an opaque surface is not
        evaluated); the colour MLP runs only for samples of weight above ``min_weight``.

        ``background`` is [C] or [R, C]. Samples sit where an unlimited march would put them,
        so the result differs only by the dropped tail (< ``min_transmittance``) and the
        skipped weights (< ``min_weight`` each): on lego models, 71-79 dB (PSNR) from the exact
        render (benchmarks/train_speed.py).
        """
        n, c = origins.shape[0], self.scene.channels
        t_near, t_far, hit = ray_aabb(origins, dirs, self.aabb)
        dir_enc = self.field.dir_encoding(dirs)  # [R, 16]: once per ray, gathered per sample
        rgb = torch.zeros(n, c, device=self.device)
        trans = torch.ones(n, device=self.device)
        alive = hit.nonzero().squeeze(1)
        t0 = t_near.clone()
        limit = self.cfg.max_samples_per_ray
        while alive.numel():
            o, d, t_end, m = origins[alive], dirs[alive], t_far[alive], alive.numel()
            s = self.march(
                o, d, t0[alive], t_end, self.step_size, self.grid, self.aabb, limit,
                max_kept=RENDER_ROUND,
            )  # fmt: skip
            t0[alive] = s.t_resume
            if s.n == 0:
                alive = alive[s.t_resume < t_end]
                continue
            ri, t_s, t_e = s.ray_indices, s.t_starts, s.t_ends
            pts = torch.addcmul(o[ri], d[ri], (0.5 * (t_s + t_e))[:, None])
            parts = _in_chunks(self.field.geometry, pts)
            sigmas, geo = torch.cat([p[0] for p in parts]), torch.cat([p[1] for p in parts])
            tau = sigmas * (t_e - t_s)
            tr_alive = trans[alive]
            w, _ = packed_weights(tau, ri, m)
            w = w * tr_alive[ri]
            use = (w > min_weight).nonzero().squeeze(1)  # colour only where it shows
            colors = torch.cat(
                _in_chunks(self.field.color_from_encoding, geo[use], dir_enc[alive[ri[use]]])
                or [geo.new_zeros(0, c)]
            )
            rgb.index_add_(0, alive[ri[use]], w[use, None] * colors)
            tr_alive = tr_alive * torch.exp(-accumulate(tau, ri, m))
            trans[alive] = tr_alive
            alive = alive[(tr_alive > min_transmittance) & (s.t_resume < t_end)]
        bg = background.expand(n, c) if background.ndim == 1 else background
        return (rgb + trans[:, None] * bg).clamp(0, 1)

    def evaluate(self, test: Dataset, views=None, progress: bool = False) -> dict:
        """PSNR/SSIM (scikit-image, stored resolution) of test views against ground truth
        composited on the dataset background: {"psnr", "ssim", "per_view": [...]}."""
        from .evaluate import evaluate_views

        return evaluate_views(self.render, test, self.scene.background, views, progress)

    def evaluate_all(self, test: Dataset, progress: bool = False) -> dict:
        """:meth:`evaluate` on all test views, keeping the renders under "images"."""
        from .evaluate import evaluate_views

        return evaluate_views(self.render, test, self.scene.background, None, progress, True)

    def parameter_count(self) -> int:
        """Trainable parameters (hash table + MLPs)."""
        return self.field.parameter_count()


# --------------------------------------------------------------------------------------------
# the whole `dronecap train`
CHECKPOINT = "checkpoint.pt"
METRICS = "metrics.json"
RUN_INFO = "run.json"
COMPARE_VIEWS = 4  # test views in the ground truth | render image


def _in_chunks(fn: Callable, *tensors: torch.Tensor) -> list:
    """``fn`` applied to ``RENDER_FIELD_CHUNK`` rows of ``tensors`` at a time (all [N, ...]),
    so the MLP activations stay in cache; the list of results (empty for N = 0)."""
    chunks = (t.split(RENDER_FIELD_CHUNK) for t in tensors)
    return [fn(*rows) for rows in zip(*chunks, strict=True)]


def _config_changes(old: TrainConfig, new: TrainConfig) -> list[str]:
    """Fields (other than ``steps``) whose values differ between two configs."""
    a, b = dataclasses.asdict(old), dataclasses.asdict(new)
    return [
        k for k in a if k != "steps" and tuple(np.atleast_1d(a[k])) != tuple(np.atleast_1d(b[k]))
    ]


def _write_json(path: Path, obj: dict) -> None:
    import json

    from dronecap.files import atomic_output

    with atomic_output(path) as tmp:
        Path(tmp).write_text(json.dumps(obj, indent=2, default=float) + "\n")


def train_run(
    dataset_path,
    cfg: TrainConfig,
    out_dir,
    resume: bool = True,
    progress: bool = True,
    checkpoint_every: int = 500,
    backend: str = "auto",
) -> dict:
    """Train on a dataset file, checkpointing, then evaluate all test views; returns metrics.

    Writes into ``out_dir``: ``checkpoint.pt`` (every ``checkpoint_every`` steps, on Ctrl-C
    and at the end; a later call resumes from it when ``resume``), ``run.json`` (dataset and
    config), ``metrics.json`` (test PSNR/SSIM per view and mean, train time, ms/step,
    parameter count), ``renders/test_XXX.png``, ``compare.png`` (ground truth | render) and,
    when the GAP9 model is importable, ``cost.json``.

    Raises:
        InputError: unreadable dataset, a run dir trained with another configuration, or a
            diverged training.
    """
    from dronecap.datasets.format import open_dataset

    dataset_path = Path(dataset_path)
    out = Path(out_dir)
    ds = open_dataset(dataset_path, kinds=("dataset", "shard"))
    ckpt = out / CHECKPOINT
    if resume and ckpt.exists():
        trainer = Trainer.load(ckpt, ds, backend=backend)
        changed = _config_changes(trainer.cfg, cfg)
        if changed:
            raise InputError(
                f"was trained with a different configuration ({', '.join(changed)}); "
                "pass --no-resume to start over or choose another --out",
                out,
            )
        trainer.cfg = cfg
    else:
        trainer = Trainer(cfg, ds, backend=backend)
    _write_json(
        out / RUN_INFO,
        {
            "dataset": str(dataset_path.resolve()),
            "config": dataclasses.asdict(cfg),
            "n_max": trainer.n_max,
        },
    )
    ms: list[float] = []
    history: list[dict] = []
    bar = progress_bar(
        total=cfg.steps,
        initial=trainer.step,
        desc="train",
        unit="step",
        disable=not progress,
        dynamic_ncols=True,
    )
    try:
        while trainer.step < cfg.steps:
            log = trainer.train_step()
            ms.append(log["ms"])
            bar.update(1)
            if trainer.step % 10 == 0 or trainer.step == cfg.steps:
                bar.set_postfix(
                    loss=f"{log['loss']:.4f}",
                    psnr=f"{log['psnr']:.1f}",
                    spr=f"{log['samples'] / max(log['rays'], 1):.1f}",
                    ms=f"{np.median(ms[-50:]):.0f}",
                )
            if trainer.step % 100 == 0:
                history.append(
                    {k: log[k] for k in ("step", "loss", "psnr", "samples", "rays")}
                    | {"seconds": trainer.train_seconds}
                )
            if trainer.step % checkpoint_every == 0 or trainer.step == cfg.steps:
                trainer.save(ckpt)
    except KeyboardInterrupt:
        bar.close()
        trainer.save(ckpt)
        raise
    bar.close()
    metrics = evaluate_run(trainer, ds, out, progress)
    metrics |= {
        "dataset": str(dataset_path.resolve()),
        "steps": trainer.step,
        "train_seconds": trainer.train_seconds,
        "ms_per_step_median": float(np.median(ms)) if ms else None,
        "threads": torch.get_num_threads(),
        "history": history,
    }
    _write_json(out / METRICS, metrics)
    _write_cost(trainer, ds, out)
    return metrics


def evaluate_run(trainer: Trainer, ds: Dataset, out: Path, progress: bool = True) -> dict:
    """Evaluate all test views, write their renders and ``compare.png``; return metrics."""
    from .evaluate import ground_truth
    from .outputs import side_by_side, write_png

    res = trainer.evaluate_all(ds, progress)
    images = res.pop("images")
    for v, img in zip(res["per_view"], images, strict=True):
        write_png(out / "renders" / f"test_{v['index']:03d}.png", img)
    pairs = [
        (ground_truth(ds, v["index"], trainer.scene.background), img)
        for v, img in list(zip(res["per_view"], images, strict=True))[:COMPARE_VIEWS]
    ]
    if pairs:
        write_png(out / "compare.png", side_by_side(pairs))
    return {
        "test": res,
        "parameters": trainer.parameter_count(),
        "n_max": trainer.n_max,
        "channels": trainer.scene.channels,
        "config": dataclasses.asdict(trainer.cfg),
    }


def _write_cost(trainer: Trainer, ds: Dataset, out: Path) -> None:
    """``cost.json`` from the GAP9 model for this run's resolved configuration."""
    from dronecap.gap9.model import cost_report

    h, w = ds.hw
    cfg = trainer.cfg.replace(
        n_max=trainer.n_max,
        channels=trainer.scene.channels,
        resolution=w,
        train_images=int(training_frames(ds).size),
    )
    _write_json(out / "cost.json", cost_report(cfg))
