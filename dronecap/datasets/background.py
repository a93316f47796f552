"""A background colour read from the frames themselves: what a capture composited on a plain
colour without alpha shows around its object.

Tools write object captures as RGB on white (or black) without an alpha channel (instant-ngp
and nerfstudio scenes, renders saved as JPEG), and their transforms.json declares no
background. Trained against an unknown background such a capture has no good start: the box
paints the plain colour as fog and the object is left as a hole in it (the one-sided lego import
of benchmarks/imports_bounds.py: 15.1 dB, train views as blurred as test views). The frames say
it themselves: their border pixels are nearly all one colour. When they are, the import
declares that colour as the dataset's background (the trainer then composites on it, as on a
synthetic scene's white, and the resolver keeps the box only); camera footage, whose borders
show walls, floor and sky, keeps no background (the far field learns what lies past the box).
"""

from __future__ import annotations

import numpy as np

# Border ring: the outer BORDER_FRACTION of the image on each side (at least one pixel).
BORDER_FRACTION = 0.04
# A border pixel matches the background when every channel lies within this of its colour.
TOLERANCE = 0.06
# The colour is a background when this fraction of all border pixels matches it (a plain
# backdrop, the object inside the frames; JPEG ringing and a part of the object touching an
# edge stay under the other 10 %).
MIN_MATCHING = 0.9


def border_pixels(images: np.ndarray) -> np.ndarray:
    """Colours [P, C] in [0, 1] (float32) of the border ring of every frame of uint8 ``images``
    [N, H, W, C]."""
    n, h, w, c = images.shape
    bh, bw = max(1, round(BORDER_FRACTION * h)), max(1, round(BORDER_FRACTION * w))
    ring = np.zeros((h, w), bool)
    ring[:bh], ring[-bh:], ring[:, :bw], ring[:, -bw:] = True, True, True, True
    return images[:, ring].reshape(-1, c).astype(np.float32) / 255.0


def plain_background(images: np.ndarray) -> tuple[tuple[float, ...] | None, str]:
    """The plain background of frames without alpha, uint8 [N, H, W, C], and why.

    Returns ``(colour, why)``: ``colour`` C values in [0, 1] (the median border colour, rounded
    to 1/255) when at least :data:`MIN_MATCHING` of the border pixels lie within
    :data:`TOLERANCE` of it in every channel, else None (camera footage).
    """
    px = border_pixels(images)
    median = np.round(np.median(px, axis=0) * 255.0) / 255.0
    share = float((np.abs(px - median) <= TOLERANCE).all(1).mean())
    colour = tuple(round(float(v), 4) for v in median)
    if share >= MIN_MATCHING:
        return colour, (
            f"the frames' borders: {100 * share:.0f} % of their pixels within {TOLERANCE:g} of "
            f"{list(colour)} (a plain backdrop without alpha)"
        )
    return None, (
        f"none: {100 * share:.0f} % of the frames' border pixels near one colour "
        f"(< {100 * MIN_MATCHING:.0f} %: camera footage)"
    )
