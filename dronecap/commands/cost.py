"""`dronecap cost`: the GAP9 cost report of a configuration, the Table II check, the budget search.

dronecap cost [--preset NAME | RUN_DIR] [--platform gap9.yaml] [--set field=value ...]
              [--grid-rule trainer|fixed] [--json out.json]
dronecap cost --table2
dronecap cost --search --budget-l3 32MB [--budget-l2 1.5MB] [--budget-l1 128kB]
              [--runs runs/*/metrics.json] [--plot pareto.png] [--target-psnr 26.94]
"""

from __future__ import annotations

import argparse
import json
from dataclasses import dataclass
from pathlib import Path

from dronecap.gap9.arch import DEFAULT_GRID_RULE, GRID_RULES
from dronecap.gap9.platform import parse_bytes
from dronecap.settings import Settings as Base
from dronecap.settings import setting


def byte_size(text: str) -> int:
    """A size such as 32MB, 1.5MiB, 128kB or 4096 -> bytes (the reason when it is not one)."""
    try:
        return parse_bytes(text)
    except ValueError as err:
        raise argparse.ArgumentTypeError(str(err)) from None


@dataclass(kw_only=True)
class Settings(Base):
    """Options of ``dronecap cost``."""

    run_dir: str | None = setting(
        None,
        positional=True,
        help="a training run dir (its run.json gives the resolved configuration that was trained)",
    )
    preset: str | None = setting(None, help="a named preset (default: tiny-dronerf)")
    platform: str | None = setting(None, help="platform YAML (default: the shipped gap9/gap9.yaml)")
    set: list[str] = setting(
        factory=list,
        repeat=True,
        metavar="FIELD=VALUE",
        help="override a TrainConfig field (repeatable)",
    )
    json: str | None = setting(
        None, help="write the report here (default: RUN_DIR/cost.json, else WORKDIR/cost.json)"
    )
    spp: float = setting(13.0, help="samples per ray/pixel (default 13)")
    images: int | None = setting(
        None, minimum=1, help="training images stored aboard (default: config)"
    )
    grid_rule: str = setting(
        DEFAULT_GRID_RULE,
        choices=GRID_RULES,
        help="occupancy updates: the trainer's rule (Instant-NGP's growing interval) or fixed "
        "(every step in the warm-up, then every grid_every steps: the paper's GAP9 run)",
    )
    table2: bool = setting(False, help="compare the model with the paper's Table II")
    search: bool = setting(False, help="list configurations fitting budgets")
    budget_l3: int | None = setting(
        None, parse=byte_size, help="untiled footprint budget, e.g. 32MB (search)"
    )
    budget_l2: int | None = setting(
        None, parse=byte_size, help="L2 peak budget, e.g. 1.5MB (search)"
    )
    budget_l1: int | None = setting(
        None, parse=byte_size, help="L1 budget incl. stacks, e.g. 128kB (search)"
    )
    runs: list[str] = setting(factory=list, help="metrics.json files of measured runs")
    plot: str | None = setting(None, help="Pareto PNG (default: WORKDIR/pareto.png)")
    top: int = setting(25, minimum=1, help="configurations listed by --search")
    target_psnr: float | None = setting(
        None,
        minimum=0,
        help="--search: rank the runs (or Table II rows) by modelled GAP9 energy to this PSNR",
    )
    tolerance_db: float = setting(
        0.25,
        minimum=0,
        help="chosen = smallest footprint within this many dB of the best fitting PSNR",
    )


def platform(args: Settings):
    """The platform of --platform (the shipped GAP9 by default); InputError when unusable."""
    from dronecap.errors import InputError
    from dronecap.gap9.platform import load_platform

    if args.platform is None:
        return load_platform()
    try:
        return load_platform(args.platform)
    except FileNotFoundError as err:
        raise InputError("platform file not found", args.platform) from err
    except ValueError as err:
        raise InputError(str(err), args.platform) from err


def _config(args: Settings):
    """(TrainConfig, default JSON path, RunSamples) from RUN_DIR (the resolved configuration
    it was trained with, the samples its metrics.json records when it has one), --preset or
    the default preset (no run: the defaults), + --set."""
    from dronecap import workspace
    from dronecap.errors import InputError
    from dronecap.gap9.model import RunSamples, deployed
    from dronecap.nerf.config import apply_sets, preset
    from dronecap.nerf.resolve import check_config
    from dronecap.nerf.run_dir import COST, METRICS, read_resolved

    if args.run_dir and args.preset:
        raise InputError("give either RUN_DIR or --preset, not both")
    if args.run_dir:
        cfg = deployed(read_resolved(args.run_dir).config)
        default_out = Path(args.run_dir) / COST
        metrics = Path(args.run_dir) / METRICS
        try:  # a run still training (or never evaluated) has no metrics yet
            run = RunSamples.from_metrics(json.loads(metrics.read_text()))
        except FileNotFoundError:
            run = RunSamples()
        except (ValueError, KeyError, TypeError) as err:
            raise InputError(f"unreadable samples: {err}", str(metrics)) from err
    else:
        try:
            cfg = preset(args.preset or "tiny-dronerf")
        except KeyError as err:
            raise InputError(str(err.args[0])) from err
        default_out = workspace.resolve(args.workdir, None, workspace.COST)
        run = RunSamples()
    try:
        cfg = apply_sets(cfg, args.set)
    except (ValueError, TypeError) as err:
        raise InputError(str(err)) from err
    check_config(cfg)
    return cfg, default_out, run


def _report(args: Settings) -> int:
    from dronecap.errors import InputError
    from dronecap.files import atomic_output
    from dronecap.gap9.model import cost_report, format_report

    cfg, default_out, run = _config(args)
    try:
        rep = cost_report(
            cfg,
            platform(args),
            samples_per_pixel=args.spp,
            n_images=args.images,
            run=run,
            grid_rule=args.grid_rule,
        )
    except (ValueError, ZeroDivisionError) as err:
        raise InputError(f"impossible configuration: {err}") from err
    print(format_report(rep))
    out = Path(args.json) if args.json else default_out
    with atomic_output(out) as tmp:
        tmp.write_text(json.dumps(rep, indent=1))
    print(f"wrote {out}")
    return 0


def run(args: Settings) -> int:
    """Print the report (or the Table II comparison, or the search) and write its outputs."""
    import math

    from dronecap.errors import InputError

    if not (math.isfinite(args.spp) and args.spp > 0):
        raise InputError(f"spp must be a positive number of samples per pixel, got {args.spp}")
    if args.table2 or args.search:
        from dronecap.commands import cost_search

        return cost_search.table2(args) if args.table2 else cost_search.search(args)
    return _report(args)
