"""The far field: what a ray sees after it leaves the scene box, learned as a function of its
direction alone (content at infinity, an environment map).

The trainer models a box. A ray that leaves it used to composite onto a fixed background (the
dataset's, black for footage without alpha); real flights see walls and sky beyond any box,
and an object shot on white without alpha would have to paint its white inside the box. With a
far field the ray colour is ``C = C_box + T_exit * far(d)``: ``T_exit`` the transmittance left
when the ray leaves the box (1 for a ray that misses it), ``d`` its unit direction.

Two forms (``TrainConfig.far_field``):

- ``"sh"``: per channel the real spherical-harmonic coefficients of bands 0..3 (16 values,
  :mod:`nerf.sh`) through a sigmoid: smooth, 16 C parameters.
- ``"grid"``: per channel an equirectangular map of :data:`GRID_ROWS` x :data:`GRID_COLS`
  logits (elevation x azimuth about the scene's z axis), sampled bilinearly (the azimuth wraps
  around) through a sigmoid: sharper, 512 C parameters.

Their sizes and costs are counted without torch in :mod:`dronecap.gap9.arch`. Both start at
one colour in every direction (``TrainConfig.far_init``) and are trained with the hash table
(no weight decay). The parameters are part
of the field (its ``far`` module): FedAvg averages them with the rest (the drones of a swarm
see the same surroundings), checkpoints carry them, and a model without a far field
(``"none"``, and every checkpoint written before it existed) renders on the fixed background
exactly as before.
"""

from __future__ import annotations

import math

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor, nn

from .config import FAR_GRID_COLS as GRID_COLS
from .config import FAR_GRID_ROWS as GRID_ROWS
from .config import FAR_SH_DEGREE as SH_DEGREE
from .config import TrainConfig
from .sh import sh_dim, sh_encode

MAP_ROWS = 64  # rows of the exported environment map (2 x as many columns)


def equirect_coords(dirs: Tensor) -> tuple[Tensor, Tensor]:
    """Azimuth column and elevation row of unit directions [N, 3] in ``grid_sample``'s
    [-1, 1] coordinates of the unpadded map (x: azimuth atan2(y, x) / pi, y: elevation
    -asin(z) / (pi / 2), so +z is the top row)."""
    x, y, z = dirs.float().unbind(-1)
    az = torch.atan2(y, x) / math.pi
    el = -torch.asin(z.clamp(-1.0, 1.0)) / (0.5 * math.pi)
    return az, el


class FarField(nn.Module):
    """Colour at infinity per direction (see the module docstring).

    Args:
        kind: "sh" or "grid".
        channels: colour channels C.
        init: the colour of every direction at the start, in (0, 1).

    Parameters: ``coeffs`` [C, 16] (sh: only the constant band 0 non-zero at the start) or
    ``logits`` [C, GRID_ROWS, GRID_COLS] (grid), giving ``init`` in every direction.
    """

    def __init__(self, kind: str, channels: int, init: float = TrainConfig.far_init) -> None:
        super().__init__()
        if kind not in ("sh", "grid"):
            raise ValueError(f"a far field is 'sh' or 'grid', got {kind!r}")
        if not 0 < init < 1:
            raise ValueError(f"the far field's start colour must be in (0, 1), got {init}")
        self.kind, self.channels = kind, channels
        logit = math.log(init / (1 - init))
        if kind == "sh":
            band0 = float(sh_encode(torch.tensor([[0.0, 0.0, 1.0]]), SH_DEGREE)[0, 0])
            coeffs = torch.zeros(channels, sh_dim(SH_DEGREE))
            coeffs[:, 0] = logit / band0
            self.coeffs = nn.Parameter(coeffs)
        else:
            self.logits = nn.Parameter(torch.full((channels, GRID_ROWS, GRID_COLS), logit))

    def forward(self, dirs: Tensor) -> Tensor:
        """Colour [N, C] in (0, 1), float32, of unit directions ``dirs`` [N, 3] (finite for
        any finite parameters: the sigmoid saturates)."""
        return torch.sigmoid(self.raw(dirs))

    def raw(self, dirs: Tensor) -> Tensor:
        """Logits [N, C] (before the sigmoid) of unit directions [N, 3]."""
        if dirs.shape[0] == 0:
            return dirs.new_zeros((0, self.channels), dtype=torch.float32)
        if self.kind == "sh":
            return sh_encode(dirs.float(), SH_DEGREE) @ self.coeffs.t()
        az, el = equirect_coords(dirs)
        g = self.logits
        padded = torch.cat([g[..., -1:], g, g[..., :1]], -1)  # the azimuth wraps around
        # column c of the map (c in [-0.5, W - 0.5]) is column c + 1 of the padded one
        col = (az + 1.0) * 0.5 * GRID_COLS - 0.5
        x = (2.0 * (col + 1.0) + 1.0) / (GRID_COLS + 2) - 1.0
        grid = torch.stack([x, el], -1).view(1, 1, -1, 2)
        out = F.grid_sample(
            padded.unsqueeze(0), grid, mode="bilinear", padding_mode="border", align_corners=False
        )
        return out.view(self.channels, -1).t()


def environment_map(far: FarField, rows: int = MAP_ROWS) -> np.ndarray:
    """The far field as an equirectangular image float32 [rows, 2 rows, C] in [0, 1]: columns
    the azimuth about the scene's z axis from -180 to +180 degrees (atan2(y, x)), rows the
    elevation from +90 (top, +z) to -90 degrees, pixel centres on a regular grid."""
    el = (0.5 - (np.arange(rows) + 0.5) / rows) * np.pi
    az = ((np.arange(2 * rows) + 0.5) / (2 * rows) - 0.5) * 2.0 * np.pi
    a, e = np.meshgrid(az, el)
    d = np.stack([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)], -1).reshape(-1, 3)
    with torch.no_grad():
        out = far(torch.as_tensor(d, dtype=torch.float32)).numpy()
    return out.reshape(rows, 2 * rows, far.channels)


def far_field_record(far: FarField) -> dict:
    """What another renderer needs to draw the far field: {"kind", "channels", "sh_degree" or
    "grid_shape", "parameters" (nested lists of the logits before the sigmoid: ``coeffs`` [C,
    16] in :mod:`nerf.sh`'s order, or ``logits`` [C, rows, cols]), "colour"}."""
    if far.kind == "sh":
        shape: dict = {"sh_degree": SH_DEGREE, "parameters": far.coeffs.detach().tolist()}
    else:
        shape = {"grid_shape": [GRID_ROWS, GRID_COLS], "parameters": far.logits.detach().tolist()}
    return {
        "kind": far.kind,
        "channels": far.channels,
        **shape,
        "colour": "sigmoid(logits) per channel in [0, 1], of the unit ray direction in the "
        "scene frame; a ray's colour is C_box + T_exit * far(d)",
    }


def make_far_field(kind: str, channels: int, init: float) -> FarField | None:
    """The far field of ``kind`` ("none": None) starting at colour ``init``."""
    return None if kind == "none" else FarField(kind, channels, init)
