"""The platform a configuration is costed on: GAP9 by default, read from ``gap9/gap9.yaml``.

A :class:`Platform` holds three kinds of numbers, each one field with its unit:

- hardware (clock, cores, FPUs, memory sizes, DMA bandwidths, power, radio rate), from the GAP9
  datasheet figures the paper quotes;
- numerics of the embedded implementation (bytes of each stored quantity) and its tiling choices;
- the calibration constants of the latency model (effective throughput of each kernel class),
  fitted on the paper's published kernel latencies (see :func:`dronecap.gap9.paper.calibrate`).

Byte sizes may be written with units: ``B``, ``kB``/``MB``/``GB`` (powers of 10, as the paper
counts) or ``KiB``/``MiB``/``GiB`` (powers of 2, as RAM sizes are).
"""

from __future__ import annotations

import dataclasses
import math
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

DEFAULT_PLATFORM = Path(__file__).with_name("gap9.yaml")

_UNITS = {
    "": 1,
    "b": 1,
    "kb": 10**3,
    "mb": 10**6,
    "gb": 10**9,
    "kib": 2**10,
    "mib": 2**20,
    "gib": 2**30,
}
_SIZE = re.compile(r"^\s*([0-9]*\.?[0-9]+(?:[eE][+-]?[0-9]+)?)\s*([A-Za-z]*)\s*$")


def parse_bytes(text: str | int | float) -> int:
    """Bytes of a size such as ``32MB`` (32e6), ``1.5MiB`` (1572864), ``128kB`` or ``4096``.

    Decimal prefixes (kB, MB, GB) are powers of 10 as in the paper; binary ones (KiB, MiB, GiB)
    powers of 2. Units are case-insensitive except that bits are refused (``Mbit``, ``Mb`` is
    read as megabytes). Raises ValueError on anything else, or on a negative size.
    """
    if isinstance(text, int | float) and not isinstance(text, bool):
        value, unit = float(text), ""
    else:
        m = _SIZE.match(str(text))
        if not m:
            raise ValueError(f"not a byte size: {text!r} (examples: 32MB, 1.5MiB, 128kB, 4096)")
        value, unit = float(m.group(1)), m.group(2).lower()
    if unit not in _UNITS:
        raise ValueError(f"unknown unit {unit!r} in {text!r}; use B, kB, MB, GB, KiB, MiB or GiB")
    if value < 0:
        raise ValueError(f"negative size: {text!r}")
    return int(round(value * _UNITS[unit]))


def format_bytes(n: float) -> str:
    """A byte count in the paper's decimal units: ``3.43 MB``, ``106.5 kB``, ``512 B``."""
    for unit, scale in (("GB", 1e9), ("MB", 1e6), ("kB", 1e3)):
        if abs(n) >= scale:
            return f"{n / scale:.3g} {unit}" if n / scale < 100 else f"{n / scale:.1f} {unit}"
    return f"{n:.0f} B"


@dataclass
class Numerics:
    """Bytes of each stored quantity in the embedded implementation (mixed precision)."""

    param_bytes: int = 4  # master copy of every trainable value (fp32)
    grad_bytes: int = 4  # gradient accumulated over the tiles of a step (fp32)
    moment_bytes: int = 4  # each of Adam's two moments (fp32)
    act_bytes: int = 2  # activations and their gradients (fp16 SIMD arithmetic)
    coord_bytes: int = 4  # sample positions and ray origins/directions (fp32)
    grid_density_bytes: int = 4  # occupancy grid: EMA of the density per cell (fp32)
    grid_flag_bytes: int = 1  # occupancy grid: occupied flag per cell (one byte, one load)
    image_bytes_per_pixel: int = 1  # stored training images (the paper's 2.56 MB per 100 x 160^2)


@dataclass
class Calibration:
    """Effective throughputs of the kernel classes (fitted; see gap9.paper.calibrate)."""

    mlp_fwd_ops_per_cycle: float = (
        5.47  # fp16 SIMD matmul, forward (peak 16 = 4 FPU x 2 lanes x FMA)
    )
    mlp_bwd_ops_per_cycle: float = 5.64  # fp16 SIMD matmul, input + weight gradients
    hash_cycles_per_corner: float = 8.72  # one corner of one level: hash, weight, L2 gather/scatter
    elementwise_ops_per_cycle: float = (
        4.0  # scalar FP ops (activations, SH, rendering, Adam): 1/FPU
    )
    optimizer_ops_per_value: float = 53.9  # ops per trainable value per optimizer step (Table II)


@dataclass
class Platform:
    """A target MCU and its radio. Sizes in bytes, rates in bytes/s or bits/s, power in W."""

    name: str = "GAP9"
    clock_hz: float = 370e6  # cluster clock at 0.8 V (peak-performance point)
    cluster_cores: int = 9  # 8 workers + 1 orchestrating core
    worker_cores: int = 8  # cores that split a kernel's samples
    fpus: int = 4  # shared floating-point units of the cluster
    fp16_simd_lanes: int = 2  # fp16 lanes per FPU instruction
    l1_bytes: int = 128 * 2**10  # cluster TCDM
    l2_bytes: int = 1536 * 2**10  # SoC L2 RAM
    l3_bytes: int = 32 * 2**20  # off-chip OctaSPI RAM on the GAP9Shield
    l1_reserved_bytes: int = 18 * 2**10  # cluster stacks: 9 cores x 2 KiB, not available to kernels
    l3_l2_bytes_per_s: float = 370e6  # main DMA, L3 <-> L2
    l2_l1_bytes_per_s: float = 13.3e9  # cluster DMA, L2 <-> L1
    power_w: float = 0.060  # average SoC power at clock_hz (the paper: 370 MHz, 0.8 V -> 60 mW)
    power_source: str = "Tiny-DroNeRF paper, Sec. III-B: 370 MHz, 0.8 V -> 60 mW average (SoC)"
    l3_joules_per_byte: float = 90e-12  # L3 (off-chip PSRAM) access energy, read or write
    l3_energy_source: str = (
        "ASSUMPTION: 1.8 V x 20 mA active at 400 MB/s (no published figure found)"
    )
    link_bits_per_s: float = 15e6  # NINA-W102 Wi-Fi, rated
    level_buffers: int = 2  # hash-level slices in L2 (double-buffered: DMA of the next overlaps)
    hash_rows: str = "paper"  # "paper": T rows per level; "stored": min(T, (res+1)^3) per level
    numerics: Numerics = field(default_factory=Numerics)
    calibration: Calibration = field(default_factory=Calibration)

    def peak_ops_per_cycle(self) -> int:
        """fp16 peak of the cluster: FPUs x SIMD lanes x 2 (fused multiply-add)."""
        return self.fpus * self.fp16_simd_lanes * 2


_BYTE_FIELDS = ("l1_bytes", "l2_bytes", "l3_bytes", "l1_reserved_bytes")
_MAY_BE_ZERO = ("l1_reserved_bytes",)


def _check_numbers(obj: Any, where: str = "") -> None:
    """ValueError naming the first numeric field of a Platform/Numerics/Calibration that is
    not a finite positive number of the right kind (``l1_reserved_bytes`` may be 0)."""
    for f in dataclasses.fields(obj):
        value, default = getattr(obj, f.name), f.default
        name = f"{where}{f.name}"
        if dataclasses.is_dataclass(value):
            _check_numbers(value, f"{name}.")
            continue
        if isinstance(default, bool) or not isinstance(default, int | float):
            if isinstance(default, str) and not isinstance(value, str):
                raise ValueError(f"{name} must be text, got {value!r}")
            continue
        ok = isinstance(value, int | float) and not isinstance(value, bool)
        ok = ok and math.isfinite(value) and (isinstance(default, float) or isinstance(value, int))
        if not ok:
            kind = "an integer" if isinstance(default, int) else "a number"
            raise ValueError(f"{name} must be {kind}, got {value!r}")
        if value < 0 or (value == 0 and f.name not in _MAY_BE_ZERO):
            raise ValueError(f"{name} must be positive, got {value!r}")


def platform_from_dict(data: dict[str, Any], base: Platform | None = None) -> Platform:
    """A Platform from a (YAML) mapping; missing fields keep ``base``'s (default: GAP9 defaults).

    Byte fields accept unit strings. Unknown keys raise ValueError naming them.
    """
    base = base or Platform()
    known = {f.name for f in dataclasses.fields(Platform)}
    unknown = set(data) - known
    if unknown:
        raise ValueError(f"unknown platform fields: {', '.join(sorted(unknown))}")
    changes: dict[str, Any] = {}
    for key, value in data.items():
        if key in ("numerics", "calibration"):
            sub = getattr(base, key)
            if value is not None and not isinstance(value, dict):
                raise ValueError(f"{key} must be a mapping of fields, got {value!r}")
            sub_known = {f.name for f in dataclasses.fields(sub)}
            bad = set(value or {}) - sub_known
            if bad:
                raise ValueError(f"unknown {key} fields: {', '.join(sorted(bad))}")
            changes[key] = dataclasses.replace(sub, **(value or {}))
        elif key in _BYTE_FIELDS:
            changes[key] = parse_bytes(value)
        else:
            changes[key] = value
    platform = dataclasses.replace(base, **changes)
    if platform.hash_rows not in ("paper", "stored"):
        raise ValueError(f"hash_rows must be 'paper' or 'stored', got {platform.hash_rows!r}")
    _check_numbers(platform)
    return platform


def load_platform(path: str | Path | None = None) -> Platform:
    """Read a platform YAML (default: the shipped ``gap9/gap9.yaml``).

    Raises:
        FileNotFoundError if the file is missing; ValueError if it is not a valid description.
    """
    import yaml

    p = Path(path) if path is not None else DEFAULT_PLATFORM
    try:
        data = yaml.safe_load(p.read_text())
    except yaml.YAMLError as err:
        raise ValueError(f"{p}: not YAML ({str(err).splitlines()[0]})") from None
    except UnicodeDecodeError:
        raise ValueError(f"{p}: not a text file") from None
    if not isinstance(data, dict):
        raise ValueError(f"{p}: expected a mapping of platform fields")
    return platform_from_dict(data)
