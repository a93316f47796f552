"""Procedural gray textures for the simulator, and mip-mapped sampling by world coordinates.

The textures are built for SIFT at 160x160: piecewise-constant regions with sharp edges and
corners at several scales (quantised multi-scale noise, tiles, bricks, posters), so features
exist at 2-10 output pixels from 0.5 m to 5 m away. They are albedo maps in [0, 1], one texel
``texel`` metres wide. :class:`MipTexture` samples them with a per-sample footprint (trilinear
filtering over a mip pyramid), so far surfaces are averaged instead of aliasing.
"""

from __future__ import annotations

import numpy as np


def blob_noise(rng: np.random.Generator, shape: tuple[int, int], scale: float) -> np.ndarray:
    """Smooth random field of feature size ~``scale`` texels: float32 [H, W], mean 0, std ~1."""
    import cv2

    h, w = shape
    gh, gw = max(2, int(np.ceil(h / scale)) + 1), max(2, int(np.ceil(w / scale)) + 1)
    coarse = rng.standard_normal((gh, gw)).astype(np.float32)
    field = cv2.resize(coarse, (int(gw * scale), int(gh * scale)), interpolation=cv2.INTER_CUBIC)
    field = field[:h, :w]
    return (field - field.mean()) / max(float(field.std()), 1e-6)


def camo(
    rng: np.random.Generator, shape: tuple[int, int], scales: tuple[float, ...], levels: int = 4
) -> np.ndarray:
    """Multi-scale noise quantised to ``levels`` gray levels: blobs with sharp edges, [0, 1]."""
    field = sum(blob_noise(rng, shape, s) / (i + 1) for i, s in enumerate(scales))
    edges = np.quantile(field, np.linspace(0, 1, levels + 1)[1:-1])
    bands = np.digitize(field, edges).astype(np.float32)
    gray = rng.permutation(np.linspace(0.15, 0.9, levels)).astype(np.float32)
    return gray[bands.astype(int)]


def tiles(
    rng: np.random.Generator,
    shape: tuple[int, int],
    tile: tuple[int, int],
    grout: int,
    stagger: bool = False,
) -> np.ndarray:
    """Tiles of ``tile`` = (height, width) texels and random gray, separated by dark grout lines;
    ``stagger`` offsets every other row by half a tile (bricks). Values in [0, 1]."""
    h, w = shape
    th, tw = tile
    shade = rng.uniform(0.3, 0.85, (h // th + 2, w // tw + 2)).astype(np.float32)
    y, x = np.mgrid[0:h, 0:w]
    r = y // th
    xs = x + (r % 2) * (tw // 2) if stagger else x
    out = shade[r, xs // tw]
    out[((y % th) < grout) | ((xs % tw) < grout)] = 0.12
    return out


def add_posters(
    rng: np.random.Generator,
    canvas: np.ndarray,
    count: int,
    size: tuple[int, int],
    rows: tuple[int, int] | None = None,
) -> np.ndarray:
    """Paste ``count`` framed rectangles of random multi-scale content onto a copy of ``canvas``
    [H, W]; sides in texels within ``size``; top edges within ``rows`` if given. (No
    checkerboards: repeated patterns make SIFT match the wrong copy.)"""
    out = canvas.copy()
    h, w = out.shape
    for _ in range(count):
        ph, pw = (int(rng.integers(size[0], size[1])) for _ in range(2))
        ph, pw = min(ph, h - 2), min(pw, w - 2)
        lo, hi = rows if rows is not None else (0, h - ph)
        y0 = int(rng.integers(lo, max(lo + 1, min(hi, h - ph))))
        x0 = int(rng.integers(0, w - pw))
        content = camo(rng, (ph, pw), (pw / 3, pw / 9, pw / 25), levels=5)
        border = max(2, min(ph, pw) // 20)
        out[y0 : y0 + ph, x0 : x0 + pw] = 0.08
        out[y0 + border : y0 + ph - border, x0 + border : x0 + pw - border] = content[
            border : ph - border, border : pw - border
        ]
    return out


_ROW = 1024


class MipTexture:
    """A texture [H, W] in [0, 1] with a mip pyramid, addressed in metres.

    Texel (i, j) covers ``[j, j+1] x [i, i+1] * texel`` metres of the surface; coordinates outside
    the texture are mirrored.
    """

    def __init__(self, image: np.ndarray, texel: float) -> None:
        import cv2

        self.texel = float(texel)
        levels = [np.ascontiguousarray(image, np.float32)]
        while min(levels[-1].shape) > 8:
            levels.append(cv2.pyrDown(levels[-1]))
        self.levels = levels

    def sample(self, u: np.ndarray, v: np.ndarray, footprint: np.ndarray) -> np.ndarray:
        """Filtered values at surface coordinates.

        Args:
            u, v: float [M] metres along the texture's width and height.
            footprint: float [M] width of the pixel's footprint on the surface, metres.

        Returns:
            float32 [M] albedo in [0, 1].
        """
        import cv2

        top = len(self.levels) - 1
        lod = np.clip(np.log2(np.maximum(footprint, 1e-9) / self.texel), 0.0, top)
        lo = np.floor(lod).astype(np.int32)
        frac = (lod - lo).astype(np.float32)
        out = np.empty(len(u), np.float32)
        for level in np.unique(lo):
            sel = np.flatnonzero(lo == level)
            vals = []
            m = len(sel)
            rows = -(-m // _ROW)  # cv2.remap maps must be < 32767 wide: fold into rows
            mx, my = np.zeros((2, rows * _ROW), np.float32)
            for k in (int(level), min(int(level) + 1, top)):
                scale = 1.0 / (self.texel * 2**k)
                mx[:m] = u[sel] * scale - 0.5
                my[:m] = v[sel] * scale - 0.5
                got = cv2.remap(
                    self.levels[k],
                    mx.reshape(rows, _ROW),
                    my.reshape(rows, _ROW),
                    cv2.INTER_LINEAR,
                    borderMode=cv2.BORDER_REFLECT,
                )
                vals.append(got.ravel()[:m])
            out[sel] = vals[0] + frac[sel] * (vals[1] - vals[0])
        return out
