"""What the drone's Wi-Fi link delivers: dropped, duplicated and torn frames.

The camera captures source frames 0..N-1 at a fixed rate; the receiver gets a subset, some twice
over, some damaged. :func:`plan_stream` decides (from the seed alone, before anything is
rendered) what each delivered frame is:

- **dropped**: lost in bursts, as a congested link loses them (a two-state Gilbert model: a
  loss starts with probability ``drop / mean_burst`` per frame and lasts ~``mean_burst``
  frames); dropped frames are simply absent (gaps in the hardware frame counter);
- **duplicated**: the receiver delivers the previous frame's buffer again in the slot of a frame
  whose data did not arrive in time (same image, byte for byte; the true pose of the delivered
  frame is the pose of the image it shows);
- **torn**: packets lost mid-frame: from a row at 30-90 % of the height down, the frame is black,
  mid-gray, or shifted (the rest of the buffer moved up by the lost packets, zero-filled at the
  end), the three as the AI-deck's stream delivers them.

:func:`tear` applies a tear to an image.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

TEAR_KINDS = ("black", "gray", "shifted")
MEAN_DROP_BURST = 2.0  # frames per loss burst
PACKET_BYTES = 1024  # bytes lost per missing packet in a shifted tear


@dataclass(frozen=True)
class Delivered:
    """One received frame: the source frame it was captured as, the source frame whose image it
    shows (differs for a duplicate), and its tear (row, kind, bytes lost) if any."""

    source: int
    shows: int
    tear_row: int | None = None
    tear_kind: str | None = None
    tear_shift: int = 0

    def record(self) -> dict[str, object]:
        """JSON-able fields for flight.json (tear fields only when torn)."""
        d = asdict(self)
        return {k: v for k, v in d.items() if v is not None and (k != "tear_shift" or v)}


@dataclass(frozen=True)
class LinkDefects:
    """Fractions of source frames dropped, delivered as duplicates, and torn (0 = none)."""

    drop: float = 0.0
    duplicate: float = 0.0
    torn: float = 0.0

    def problems(self) -> list[str]:
        """Out-of-range fractions (each must be in [0, 0.5])."""
        return [
            f"--{k} must be in [0, 0.5], got {v}"
            for k, v in asdict(self).items()
            if not 0 <= v <= 0.5
        ]


def plan_stream(frames: int, link: LinkDefects, height: int, seed: int) -> list[Delivered]:
    """The delivered frames, in order, of a ``frames``-frame capture through ``link``.

    The first and last source frames are always delivered intact (so the flight's extent is
    known). ``height`` is the image height in rows (for the tear rows).
    """
    rng = np.random.default_rng([seed, 7])
    start_p = link.drop / MEAN_DROP_BURST / max(1e-9, 1.0 - link.drop)
    lost = np.zeros(frames, bool)
    i = 1
    while i < frames - 1:
        if rng.random() < start_p:
            n = int(rng.geometric(1.0 / MEAN_DROP_BURST))
            lost[i : min(i + n, frames - 1)] = True
            i += n
        else:
            i += 1
    dup = rng.random(frames) < link.duplicate
    torn = rng.random(frames) < link.torn
    rows = rng.integers(int(0.3 * height), int(0.9 * height), frames)
    kinds = rng.integers(0, len(TEAR_KINDS), frames)
    shifts = rng.integers(1, 4, frames) * PACKET_BYTES
    out: list[Delivered] = []
    for s in range(frames):
        if lost[s]:
            continue
        ends = s in (0, frames - 1)
        if dup[s] and out and not ends:  # the previous buffer again, tear and all
            prev = out[-1]
            out.append(Delivered(s, prev.shows, prev.tear_row, prev.tear_kind, prev.tear_shift))
        elif torn[s] and not ends:
            k = TEAR_KINDS[int(kinds[s])]
            shift = int(shifts[s]) if k == "shifted" else 0
            out.append(Delivered(s, s, int(rows[s]), k, shift))
        else:
            out.append(Delivered(s, s))
    return out


def tear(image: np.ndarray, row: int, kind: str, shift: int) -> np.ndarray:
    """``image`` uint8 [H, W] torn from ``row`` down: 'black' (0), 'gray' (128) or 'shifted'
    (the buffer from that row on moved up by ``shift`` bytes, zeros at the end)."""
    out = image.copy()
    if kind == "black":
        out[row:] = 0
    elif kind == "gray":
        out[row:] = 128
    elif kind == "shifted":
        flat = out.reshape(-1)
        start = row * image.shape[1]
        tail = image.reshape(-1)[start + shift :]
        flat[start : start + len(tail)] = tail
        flat[start + len(tail) :] = 0
    else:
        raise ValueError(f"unknown tear kind {kind!r}")
    return out
