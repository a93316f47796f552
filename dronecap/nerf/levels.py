"""The hash grid's level sizes: the one formula the encoder and the GAP9 cost model share.

Level ``l`` of ``L`` has ``floor(n_min * b**l)`` cells per axis, ``b = exp(ln(n_max/n_min)/(L-1))``
(``b = 1`` for one level), and stores ``min(T, (res_l + 1)**3)`` table rows. No torch here, so
the cost model can import it cheaply.
"""

from __future__ import annotations

import math
from collections.abc import Sequence


def level_resolutions(levels: int, n_min: int, n_max: int) -> list[int]:
    """Cells per axis of each level: ``floor(n_min * b**l)``, geometric from n_min to n_max.

    A relative guard of 1e-9 keeps ``n_min * b**(L-1)`` from rounding down to ``n_max - 1``.
    """
    if levels < 1 or n_min < 1 or n_max < n_min:
        raise ValueError(
            f"need levels >= 1 and 1 <= n_min <= n_max, got {levels}, {n_min}, {n_max}"
        )
    b = math.exp(math.log(n_max / n_min) / (levels - 1)) if levels > 1 else 1.0
    return [int(math.floor(n_min * b**lvl * (1 + 1e-9))) for lvl in range(levels)]


def level_offsets(resolutions: Sequence[int], log2_hashmap: int) -> list[int]:
    """Start row of each level in the table (``len = levels + 1``, last = total rows).

    Level ``l`` uses ``min(2**log2_hashmap, (res_l + 1)**3)`` rows.
    """
    offsets = [0]
    for res in resolutions:
        offsets.append(offsets[-1] + min(1 << log2_hashmap, (res + 1) ** 3))
    return offsets
