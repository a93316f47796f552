"""``dronecap simulate``: render a synthetic nano-drone flight (video or drone capture folder plus
ground truth), optionally through a realistic lens, sensor and Wi-Fi link.

Each defect flag given without a value takes its realistic default level
(``dronecap.simulator.sensor.DEFECT_DEFAULTS``); ``--sensor aideck`` turns them all on at
324x244. With no flag the output is the original clean simulator's.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from dronecap.settings import Numbers, Size, numbers, setting
from dronecap.settings import Settings as Base
from dronecap.simulator.sensor import DEFECT_DEFAULTS

SCENES = ("corridor", "orbit")
CODECS = ("ffv1", "mjpg", "mp4v")
FORMATS = ("mp4", "nanocockpit", "pulp-dronet")
SENSORS = ("clean", "aideck", "aideck-162")


def _pixel_size(text: str) -> Size:
    """``"WxH"`` -> (width, height) in pixels (ValueError when it is not one)."""
    try:
        w, h = (int(x) for x in text.lower().split("x"))
    except ValueError:
        raise ValueError(f"must be WxH, got {text!r}") from None
    return Size((w, h))


def _number(text: str) -> float:
    """One finite number (ValueError when it is not one)."""
    return numbers(1)(text)[0]


def _whole(text: str) -> int:
    """A whole number, also written as a float (``60.0``); ValueError when it is not one."""
    value = _number(text)
    if value != int(value):
        raise ValueError(f"must be an integer, got {text!r}")
    return int(value)


def _defect(name: str, metavar: str, text: str, parse: Callable[[str], Any] = _number) -> Any:
    """A defect option: given alone, it takes its realistic level from DEFECT_DEFAULTS."""
    level = DEFECT_DEFAULTS[name]
    shown = ",".join(str(x) for x in level) if isinstance(level, tuple) else str(level)
    return setting(
        None,
        const=shown,
        parse=parse,
        late=True,
        metavar=metavar,
        help=f"{text}; given alone: {shown}",
    )


@dataclass(kw_only=True)
class Settings(Base):
    """Options of ``dronecap simulate``."""

    scene: str = setting("corridor", choices=SCENES, help="scene")
    output: str | None = setting(
        None,
        short="-o",
        help="video file (default: WORKDIR/flight.mp4; ground truth beside it as .json) or, "
        "for a folder format, the capture folder (default: WORKDIR/capture; flight.json inside)",
    )
    frames: int = setting(600, help="source frames at 30 Hz (per drone)")
    drones: int = setting(
        1,
        minimum=1,
        maximum=16,
        help="a swarm of N drones, each flying its own overlapping part of the scene with its own"
        " camera and onboard state, one entry per drone in the output folder (default: WORKDIR/"
        "swarm; swarm.json lists them)",
    )
    seed: int = setting(0, minimum=0, help="random seed (>= 0)")
    codec: str = setting(
        "ffv1",
        choices=CODECS,
        help="mp4 format: ffv1 = lossless (best for SIFT); mjpg / mp4v = smaller, lossy",
    )
    format: str = setting(
        "mp4",
        choices=FORMATS,
        help="mp4: a video; nanocockpit: camera_raw/*.png + metadata.csv; pulp-dronet: "
        "images/<ticks>.jpeg + state.csv (both with noisy, drifting onboard state)",
    )
    sensor: str = setting(
        "clean",
        choices=SENSORS,
        help="clean: 160x160 pinhole, mild noise; aideck: HM01B0 at 324x244 (f 184 px) with "
        "every defect at its default level; aideck-162: the same binned to 162x162",
    )
    size: Size | None = setting(
        None, parse=_pixel_size, late=True, metavar="WxH", help="image size (default: the sensor's)"
    )
    focal: float | None = setting(None, help="focal length in pixels (default: the sensor's)")
    distortion: Numbers | None = _defect(
        "distortion", "K1,K2", "OpenCV radial lens distortion (also K1,K2,K3)", numbers(2, 3)
    )
    principal_offset: Numbers | None = _defect(
        "principal_offset", "DX,DY", "principal point off centre by DX*width, DY*height", numbers(2)
    )
    vignetting: float | None = _defect("vignetting", "V", "light lost at the farthest corner (0-1)")
    noise: Numbers | None = _defect(
        "noise", "READ,SHOT", "read noise DN and shot noise DN^2 per DN", numbers(2)
    )
    blur: float | None = _defect(
        "blur", "MS", "exposure time in ms (motion blur from the flight's own motion)"
    )
    exposure_drift: float | None = _defect(
        "exposure_drift", "A", "relative amplitude of the auto-exposure gain drift (0-1)"
    )
    jpeg: int | None = _defect("jpeg", "Q", "JPEG quality of the streamed frames (1-100)", _whole)
    drop: float | None = _defect(
        "drop", "RATE", "fraction of frames lost by the link, in bursts (0-0.5)"
    )
    duplicate: float | None = _defect(
        "duplicate", "RATE", "fraction of frames delivered as the previous buffer (0-0.5)"
    )
    torn: float | None = _defect(
        "torn", "RATE", "fraction of frames whose bottom part is black/gray/shifted (0-0.5)"
    )
    state_noise: Numbers | None = setting(
        None,
        parse=numbers(4),
        late=True,
        metavar="POS_MM,ANGLE_DEG,SCALE,YAW_DRIFT",
        help="folder formats: onboard estimate errors: white position noise (mm), attitude "
        "noise (deg), odometry scale error (fraction), heading drift (deg/min) "
        "(default: 5,0.5,0.01,2)",
    )


DEFECTS = tuple(DEFECT_DEFAULTS)  # the defect options, by field name


def capture_from_settings(args: Settings):  # noqa: ANN201 - a simulate.Capture
    """The :class:`~dronecap.simulator.simulate.Capture` the options describe (range-checked)."""
    import dataclasses

    from dronecap.errors import InputError
    from dronecap.simulator.sensor import default_lens, with_lens_defects
    from dronecap.simulator.simulate import Capture, capture_preset

    preset = capture_preset(args.sensor)
    sensor, link, state = preset.sensor, preset.link, preset.state_noise
    lens = sensor.lens
    if args.size is not None or args.focal is not None:
        w, h = lens.width, lens.height
        if args.size is not None:
            w, h = args.size
            if not (16 <= w <= 2048 and 16 <= h <= 2048):
                raise InputError(f"--size must be 16-2048 pixels a side, got {args.size}")
        if args.focal is not None and not (math.isfinite(args.focal) and args.focal > 0):
            raise InputError(f"--focal must be a positive number of pixels, got {args.focal}")
        focal = args.focal if args.focal is not None else lens.fx * w / lens.width
        new = default_lens(w, h, focal)
        offset = (
            (lens.cx - lens.width / 2) / lens.width,
            (lens.cy - lens.height / 2) / lens.height,
        )
        lens = with_lens_defects(new, None, offset)
        lens = dataclasses.replace(lens, model=sensor.lens.model, distortion=sensor.lens.distortion)
    v = {k: getattr(args, k) for k in DEFECTS}
    if v["principal_offset"] is not None:
        dx, dy = v["principal_offset"]
        if not (abs(dx) < 0.4 and abs(dy) < 0.4):
            raise InputError("--principal-offset must be within +-0.4 of the size")
        lens = dataclasses.replace(lens, cx=lens.width * (0.5 + dx), cy=lens.height * (0.5 + dy))
    if v["distortion"] is not None:
        k = tuple(v["distortion"])
        if not all(abs(x) <= 1.0 for x in k):
            raise InputError("--distortion coefficients must be within +-1")
        lens = with_lens_defects(lens.pinhole(), k)
    changes: dict[str, object] = {"lens": lens}
    if v["vignetting"] is not None:
        changes["vignetting"] = v["vignetting"]
    if v["noise"] is not None:
        changes["read_noise"], changes["shot_noise"] = v["noise"]
    if v["blur"] is not None:
        ms = v["blur"]
        if not 0 < ms <= 1000 / 30:
            raise InputError(f"--blur is an exposure time in ms within (0, 33.3], got {ms}")
        changes["exposure_s"] = ms / 1000
        changes["max_subframes"] = max(sensor.max_subframes, 16)
    if v["exposure_drift"] is not None:
        changes["exposure_drift"] = v["exposure_drift"]
    if v["jpeg"] is not None:
        if not 1 <= v["jpeg"] <= 100:
            raise InputError(f"--jpeg quality must be an integer 1-100, got {v['jpeg']}")
        changes["jpeg_quality"] = v["jpeg"]
    sensor = dataclasses.replace(sensor, **changes)  # type: ignore[arg-type]
    for name in ("drop", "duplicate", "torn"):
        if v[name] is not None:
            link = dataclasses.replace(link, **{name: v[name]})
    if args.state_noise is not None:
        pos, ang, scale, yaw = args.state_noise
        state = dataclasses.replace(
            state, position_mm=pos, angle_deg=ang, scale=scale, yaw_drift_deg_min=yaw
        )
    named = args.sensor if not any(x is not None for x in v.values()) else "custom"
    capture = Capture(sensor, link, state, named)
    if problems := capture.problems():
        raise InputError("; ".join(problems))
    return capture


def run(args: Settings) -> int:
    """Render the flight and print where it went."""
    from dronecap import workspace
    from dronecap.errors import InputError
    from dronecap.simulator.simulate import simulate

    if args.frames < 2 or args.frames > 100_000:
        raise InputError(f"--frames must be 2-100000, got {args.frames}")
    capture = capture_from_settings(args)
    if args.drones > 1:
        return _run_swarm(args, capture)
    default = "flight.mp4" if args.format == "mp4" else "capture"
    out = workspace.resolve(args.workdir, args.output, default)
    t0 = time.perf_counter()
    path, gt = simulate(
        args.scene,
        out,
        frames=args.frames,
        seed=args.seed,
        codec=args.codec,
        capture=capture,
        fmt=args.format,
    )
    dt = time.perf_counter() - t0
    print(
        f"rendered {args.frames} frames of '{args.scene}' (seed {args.seed}, sensor "
        f"{capture.sensor_name}) in {dt:.1f} s ({args.frames / dt:.0f} frames/s) -> {path}, "
        f"ground truth {gt}"
    )
    return 0


def _run_swarm(args: Settings, capture: Any) -> int:
    """``--drones N`` (N >= 2): render the swarm's flights into one folder."""
    from dronecap import workspace
    from dronecap.simulator.swarm import simulate_swarm

    out = workspace.resolve(args.workdir, args.output, "swarm")
    t0 = time.perf_counter()
    simulate_swarm(
        args.scene, out, args.drones, args.frames, args.seed, args.codec, capture, args.format
    )
    print(
        f"rendered {args.drones} drones x {args.frames} frames of '{args.scene}' (seed "
        f"{args.seed}, sensor {capture.sensor_name}) in {time.perf_counter() - t0:.1f} s -> {out}"
        f" (one {'video' if args.format == 'mp4' else 'folder'} per drone, swarm.json)"
    )
    return 0
