"""The Tiny-DroNeRF radiance field: hash encoding, density MLP, SH + colour MLP.

Points are in scene units and mapped to the unit cube of the dataset's AABB before encoding.
The colour head has as many channels as the data (1 gray, 3 RGB).
"""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor, nn

from .config import TrainConfig, mlp_dtype
from .far_field import make_far_field
from .hashgrid import HashGrid, Visible
from .mlp_kernel import amx, field_outputs, mlp_weights, usable
from .sh import sh_dim, sh_encode

DTYPES = {"fp32": torch.float32, "fp16": torch.float16, "bf16": torch.bfloat16}
MAX_LOG_DENSITY = 15.0  # exp(15) ~ 3.3e6 per scene unit: opaque at any step size in use
# bf16 products pad their rows to a multiple of this: oneDNN builds a kernel for every new
# matrix shape (~0.4 ms each), and the sample count changes at every step
ROW_QUANTUM = 256


def storage_dtype(precision: str) -> torch.dtype:
    """torch dtype of a ``TrainConfig.precision`` name ("fp32", "fp16", "bf16")."""
    if precision not in DTYPES:
        raise ValueError(f"precision must be one of {sorted(DTYPES)}, got {precision!r}")
    return DTYPES[precision]


def round_to(x: Tensor, dtype: torch.dtype) -> Tensor:
    """``x`` rounded to ``dtype`` and back to float32 (gradient passes straight through)."""
    return x if dtype == torch.float32 else x.to(dtype).to(torch.float32)


def trunc_exp(x: Tensor) -> Tensor:
    """Density activation exp(x) with x clamped to [-15, 15]: never overflows, even in fp16."""
    return torch.exp(x.clamp(-MAX_LOG_DENSITY, MAX_LOG_DENSITY))


def _mlp(n_in: int, hidden: int, layers: int, n_out: int) -> nn.Sequential:
    """Bias-free ReLU MLP with ``layers`` hidden layers of ``hidden`` units (as tcnn's)."""
    mods: list[nn.Module] = []
    width = n_in
    for _ in range(layers):
        mods += [nn.Linear(width, hidden, bias=False), nn.ReLU()]
        width = hidden
    mods.append(nn.Linear(width, n_out, bias=False))
    return nn.Sequential(*mods)


class Field(nn.Module):
    """Hash grid + density MLP (density, geometry features) + colour MLP on SH of directions.

    Args:
        cfg: levels, features, log2_hashmap, n_min, n_max, hidden, layer counts, geo_features,
            sh_degree, precision, far_field; a resolved config (``n_max`` and ``far_field`` are
            used as they stand, see :mod:`nerf.resolve`; an unresolved "auto" far field builds
            none).
        channels: colour channels C of the head (1 or 3, or any other count).
        aabb: [2, 3] bounds in scene units; points are normalised to the unit cube over it.
        backend: hash-grid backend ("auto", "cpp", "torch", "compile").

    The MLPs multiply in ``cfg.mlp_dtype`` (:func:`nerf.config.mlp_dtype`); their weights are
    float32 either way and every output is float32.
    """

    def __init__(
        self, cfg: TrainConfig, channels: int, aabb: np.ndarray, backend: str = "auto"
    ) -> None:
        super().__init__()
        self.dtype = storage_dtype(cfg.precision)
        self.product_dtype = DTYPES[mlp_dtype(cfg)]
        self.channels = channels
        self.encoding = HashGrid(
            cfg.levels, cfg.features, cfg.log2_hashmap, cfg.n_min, cfg.n_max, backend, self.dtype
        )
        self.density_mlp = _mlp(
            self.encoding.out_dim, cfg.hidden, cfg.density_layers, cfg.geo_features
        )
        self.sh_degree = cfg.sh_degree
        n_in = cfg.geo_features + sh_dim(cfg.sh_degree)
        self.color_mlp = _mlp(n_in, cfg.hidden, cfg.color_layers, channels)
        kind = cfg.far_field if cfg.far_field in ("sh", "grid") else "none"
        self.far = make_far_field(kind, channels, cfg.far_init)  # past the box (nerf.far_field)
        a = torch.as_tensor(np.asarray(aabb), dtype=torch.float32)
        self.register_buffer("aabb_min", a[0].clone(), persistent=False)
        self.register_buffer("aabb_size", (a[1] - a[0]).clone(), persistent=False)
        self._fused_mlp: bool | None = None  # decided by prepare_kernels (builds them)
        self._weights: list[Tensor] | None = None  # the fused MLPs' five weights, once listed

    def _run(self, mlp: nn.Sequential, x: Tensor, outputs: int | None = None) -> Tensor:
        """Apply ``mlp`` to ``x`` [N, n_in] float32 -> [N, n_out] float32 (only the first
        ``outputs`` columns of the last layer when given: [N, outputs]).

        In fp32 products every activation is rounded to the storage dtype (GAP9 emulation).
        The ReLUs work in place (a ReLU of a rounded value needs no rounding), with autograd
        too: a bias-free linear layer's backward needs its input and weight, not its output.
        In bf16 products (storage fp32 or bf16) the activations are bf16 and the rows are
        padded with zeros to a multiple of :data:`ROW_QUANTUM` (zero rows stay zero and add
        nothing to the weight gradients).
        """
        last = len(mlp) - 1
        if self.product_dtype == torch.float32:
            for i, layer in enumerate(mlp):
                if isinstance(layer, nn.ReLU):
                    x = torch.relu_(x)
                else:
                    w = layer.weight if i < last or outputs is None else layer.weight[:outputs]
                    x = round_to(F.linear(x, w), self.dtype)
            return x
        n = x.shape[0]
        rows = -(-n // ROW_QUANTUM) * ROW_QUANTUM
        h = x.new_zeros((rows, x.shape[1]), dtype=self.product_dtype)
        h[:n] = x
        for i, layer in enumerate(mlp):
            if isinstance(layer, nn.ReLU):
                h = torch.relu_(h)
            else:
                w = layer.weight if i < last or outputs is None else layer.weight[:outputs]
                h = F.linear(h, w.to(self.product_dtype))
        return h[:n].float()

    def unit(self, points: Tensor) -> Tensor:
        """``points`` [N, 3] in scene units mapped to the unit cube of the AABB (what the hash
        encoding takes; outside the box lies outside [0, 1])."""
        return (points - self.aabb_min) / self.aabb_size

    def encode(self, points: Tensor) -> Tensor:
        """Hash encoding [N, levels * features] float32 of ``points`` [N, 3] (scene units)."""
        return self.encoding(self.unit(points))

    def geometry(self, points: Tensor, encoded: Tensor | None = None) -> tuple[Tensor, Tensor]:
        """Density and geometry features.

        Args:
            points: [N, 3] scene units (outside the AABB is clamped to its faces).
            encoded: :meth:`encode` of ``points`` computed earlier without autograd, or None;
                given, the encoding is not computed again and its table gradient still flows.

        Returns:
            sigma [N] density per scene unit (>= 0, finite), geo [N, geo_features].
        """
        unit = self.unit(points)
        return self.geometry_from_encoding(self.encoding(unit, cached=encoded))

    def geometry_from_encoding(self, encoded: Tensor) -> tuple[Tensor, Tensor]:
        """Density [N] per scene unit and geometry features [N, geo_features] from a hash
        encoding [N, levels * features] (:meth:`encode`)."""
        h = self._run(self.density_mlp, round_to(encoded, self.dtype))
        return trunc_exp(h[:, 0]), h

    def density_from_encoding(self, encoded: Tensor) -> Tensor:
        """Density [N] per scene unit from a hash encoding [N, levels * features]: the density
        MLP's first output alone (its last layer computes 1 column, not ``geo_features``; the
        pre-pass of compaction and the occupancy updates need no geometry features)."""
        return trunc_exp(self._run(self.density_mlp, round_to(encoded, self.dtype), 1)[:, 0])

    def density(self, points: Tensor) -> Tensor:
        """Density [N] per scene unit at ``points`` [N, 3] (without autograd when it is off:
        :meth:`density_and_encoding`)."""
        if not torch.is_grad_enabled():
            return self.density_and_encoding(points, keep_encoded=False)[0]
        return self.density_from_encoding(self.encode(points))

    @torch.no_grad()
    def density_and_encoding(
        self, points: Tensor, keep_encoded: bool = True
    ) -> tuple[Tensor, Tensor | None]:
        """Density [N] per scene unit at ``points`` [N, 3] and, with ``keep_encoded``, their
        hash encoding [N, levels * features] (:meth:`encode`), without autograd.

        With fp32 storage, a density MLP of one hidden layer and the C++ kernel, encoding and
        MLP run fused (:meth:`HashGrid.fused_density`; the same values up to float32 summation
        order, or bf16 products on the AMX tiles under ``mlp_dtype`` bf16), else one after the
        other.
        """
        unit = self.unit(points)
        layers = self._density_rows()
        if layers is not None:
            fused = self.encoding.fused_density(unit, *layers, keep_encoded, self._amx_bf16())
            if fused is not None:
                return trunc_exp(fused[0]), fused[1]
        encoded = self.encoding(unit)
        return self.density_from_encoding(encoded), (encoded if keep_encoded else None)

    @torch.no_grad()
    def visible_samples(
        self,
        origins: Tensor,
        dirs: Tensor,
        samples: tuple[Tensor, Tensor, Tensor],
        min_transmittance: float,
        max_kept: int = 0,
    ) -> Visible | None:
        """Compaction's pre-pass fused in C++ (:meth:`HashGrid.fused_visible`): of packed
        samples ``samples`` = (t_starts, t_ends, ray_indices) on rays ``origins``, ``dirs``
        [R, 3] (scene units), those whose transmittance is above ``min_transmittance``, with
        their hash encodings and their midpoints in the box's unit cube (what was encoded);
        with ``max_kept`` > 0 only the first whole rays whose kept samples fit in it; None when
        the fused kernels cannot run this field (:meth:`density_and_encoding`'s conditions)."""
        layers = self._density_rows()
        if layers is None:
            return None
        box = torch.stack([self.aabb_min, self.aabb_size])  # as :meth:`unit` maps
        return self.encoding.fused_visible(
            (origins, dirs, box),
            samples,
            *layers,
            MAX_LOG_DENSITY,
            min_transmittance,
            self._amx_bf16(),
            max_kept,
        )

    @torch.no_grad()
    def grid_refresh(
        self, density: Tensor, allowed: Tensor | None, cells: Tensor, jitter: Tensor,
        aabb: Tensor, res: int, step_size: float, decay: float, threshold: float,
    ) -> tuple[Tensor, Tensor] | None:  # fmt: skip
        """An occupancy-grid update after its draws in one C++ call (``refresh`` of
        :func:`nerf.occupancy.update`, whose arguments these are): the density of each
        sampled cell at its jittered point (encoding and density MLP fused, as
        :meth:`density_and_encoding`), folded into the grid; None where the fused queries
        cannot run this field."""
        layers = self._density_rows()
        if layers is None:
            return None
        box = torch.stack([self.aabb_min, self.aabb_size])  # as :meth:`unit` maps
        grid = (density, allowed, aabb, res, step_size, decay, threshold)
        mlp = (*layers, MAX_LOG_DENSITY)
        return self.encoding.fused_grid_refresh(grid, cells, jitter, box, mlp, self._amx_bf16())

    def _density_rows(self) -> tuple[Tensor, Tensor] | None:
        """(hidden-layer weight, the density's output row) of a density MLP of one hidden
        layer, which the fused C++ queries take; else None. Under bf16 products they multiply
        the hidden layer on the AMX tiles too (bf16 inputs, float32 sums; the ReLU and the
        density row in float32), else in float32."""
        layers = [m for m in self.density_mlp if isinstance(m, nn.Linear)]
        if len(layers) != 2:
            return None
        return layers[0].weight, layers[1].weight[0]

    def forward(self, points: Tensor, dirs: Tensor) -> tuple[Tensor, Tensor]:
        """Colour and density.

        Args:
            points: [N, 3] scene units.
            dirs: [N, 3] unit view directions.

        Returns:
            color [N, C] in (0, 1), sigma [N] per scene unit.
        """
        sigma, geo = self.geometry(points)
        return self.color(geo, dirs), sigma

    def prepare_kernels(self) -> bool:
        """Build (once, cached on disk) or load the C++ kernels this field uses, so that the
        first training step does not pay for a build inside a time budget; whether the fused
        MLPs (:meth:`color_sigma`) can run this field."""
        if self._fused_mlp is None:
            self.encoding.prepare()
            self._fused_mlp = self.dtype == torch.float32 and usable(
                self.density_mlp, self.color_mlp, self.encoding.backend
            )
        return self._fused_mlp and (self.product_dtype == torch.float32 or self._amx_bf16())

    def mlp_kernel_args(self) -> tuple[list[Tensor], bool, float] | None:
        """What :mod:`nerf.mlp_kernel` runs this field's MLPs with: (the five weights, whether
        it multiplies in bf16, the density logit's clamp); None where the torch layers do."""
        if not self.prepare_kernels():
            return None
        if self._weights is None:  # the same Parameter objects for the module's life
            self._weights = mlp_weights(self.density_mlp, self.color_mlp)
        return self._weights, self._amx_bf16(), float(MAX_LOG_DENSITY)

    def _amx_bf16(self) -> bool:
        """Whether the MLPs multiply in bf16 and the fused kernel can do so on AMX tiles."""
        return self.product_dtype == torch.bfloat16 and amx()

    def color_sigma(
        self, unit: Tensor, dir_enc: Tensor, ray_indices: Tensor, encoded: Tensor | None = None
    ) -> tuple[Tensor, Tensor]:
        """Colour [N, C] in (0, 1) and density [N] per scene unit of samples, with autograd
        (the training pass).

        Args:
            unit: [N, 3] the samples in the box's unit cube (:meth:`unit` of scene points).
            dir_enc: [R, sh_degree^2] :meth:`dir_encoding` of each ray's direction.
            ray_indices: [N] int64, each sample's ray.
            encoded: the hash encoding of ``unit`` computed earlier without autograd, or None
                (as in :meth:`geometry`).

        The fused C++ MLPs (:mod:`nerf.mlp_kernel`) when they can run this field (float32
        storage and the presets' layer shapes), else the torch layers; the same values and
        gradients up to float32 summation order (in fp32 products).
        """
        enc = self.encoding(unit, cached=encoded)
        kernel_args = self.mlp_kernel_args()
        if kernel_args is not None:
            return field_outputs(enc, dir_enc, ray_indices, *kernel_args)
        sigma, geo = self.geometry_from_encoding(enc)
        return self.color_from_encoding(geo, dir_enc[ray_indices]), sigma

    def color(self, geo: Tensor, dirs: Tensor) -> Tensor:
        """Colour [N, C] in (0, 1) from geometry features [N, geo_features] and unit view
        directions [N, 3]."""
        return self.color_from_encoding(geo, self.dir_encoding(dirs))

    def dir_encoding(self, dirs: Tensor) -> Tensor:
        """SH encoding [N, sh_degree^2] of unit directions [N, 3], in the storage precision.

        A ray's samples share its direction: renderers encode once per ray and gather.
        """
        return round_to(sh_encode(dirs, self.sh_degree, self.encoding.backend), self.dtype)

    def color_from_encoding(self, geo: Tensor, dir_enc: Tensor) -> Tensor:
        """Colour [N, C] in (0, 1) from geometry features [N, geo_features] and encoded
        directions [N, sh_degree^2] (:meth:`dir_encoding`)."""
        return torch.sigmoid(self._run(self.color_mlp, torch.cat([geo, dir_enc], -1)))

    def behind(self, dirs: Tensor, background: Tensor) -> Tensor:
        """What a ray sees when it leaves the box: the far field's colour [R, C] of its unit
        direction ``dirs`` [R, 3] when the model has one, else ``background`` ([C] or [R, C],
        the fixed background)."""
        return background if self.far is None else self.far(dirs)

    def far_parameters(self) -> list[nn.Parameter]:
        """The far field's parameters (none without one; trained with the hash table)."""
        return [] if self.far is None else list(self.far.parameters())

    def mlp_parameters(self) -> list[nn.Parameter]:
        """The MLP weights (the ones that get L2 weight decay)."""
        return [*self.density_mlp.parameters(), *self.color_mlp.parameters()]

    def parameter_count(self) -> int:
        """Trainable parameters (hash table + MLPs + far field)."""
        return sum(p.numel() for p in self.parameters())
