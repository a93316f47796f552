"""`dronecap cost`: the GAP9 cost report of a configuration, the Table II check, the budget search.

dronecap cost [--preset NAME | RUN_DIR] [--platform gap9.yaml] [--set field=value ...]
              [--json out.json]
dronecap cost --table2
dronecap cost --search --budget-l3 32MB [--budget-l2 1.5MB] [--budget-l1 128kB]
              [--runs runs/*/metrics.json] [--plot pareto.png]
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

from dronecap.stage import Settings as Base
from dronecap.stage import setting


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
    images: int | None = setting(None, help="training images stored aboard (default: config)")
    table2: bool = setting(False, help="compare the model with the paper's Table II")
    search: bool = setting(False, help="list configurations fitting budgets")
    budget_l3: str | None = setting(None, help="untiled footprint budget, e.g. 32MB (search)")
    budget_l2: str | None = setting(None, help="L2 peak budget, e.g. 1.5MB (search)")
    budget_l1: str | None = setting(None, help="L1 budget incl. stacks, e.g. 128kB (search)")
    runs: list[str] = setting(factory=list, help="metrics.json files of measured runs")
    plot: str | None = setting(None, help="Pareto PNG (default: WORKDIR/pareto.png)")
    top: int = setting(25, help="configurations listed by --search")
    tolerance_db: float = setting(
        0.25, help="chosen = smallest footprint within this many dB of the best fitting PSNR"
    )


def _platform(args: Settings):
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
    """(TrainConfig, default JSON path) from RUN_DIR (the resolved configuration it was
    trained with), --preset or the default preset, + --set."""
    from dronecap import workspace
    from dronecap.errors import InputError
    from dronecap.nerf.config import apply_sets, preset
    from dronecap.nerf.resolve import check_config
    from dronecap.nerf.run_dir import COST, read_resolved

    if args.run_dir and args.preset:
        raise InputError("give either RUN_DIR or --preset, not both")
    if args.run_dir:
        from dronecap.gap9.model import deployed

        cfg = deployed(read_resolved(args.run_dir).config)
        default_out = Path(args.run_dir) / COST
    else:
        try:
            cfg = preset(args.preset or "tiny-dronerf")
        except KeyError as err:
            raise InputError(str(err.args[0])) from err
        default_out = workspace.resolve(args.workdir, None, "cost.json")
    try:
        cfg = apply_sets(cfg, args.set)
    except (ValueError, TypeError) as err:
        raise InputError(str(err)) from err
    check_config(cfg)
    return cfg, default_out


def _check_options(args: Settings) -> None:
    """Range-check the numeric options before any work (one line each)."""
    import math

    from dronecap.errors import InputError

    if not (math.isfinite(args.spp) and args.spp > 0):
        raise InputError(f"--spp takes a positive number of samples per pixel, got {args.spp}")
    if args.images is not None and args.images < 1:
        raise InputError(f"--images takes a positive number of images, got {args.images}")
    if args.top < 1:
        raise InputError(f"--top takes a positive count, got {args.top}")
    if not (math.isfinite(args.tolerance_db) and args.tolerance_db >= 0):
        raise InputError(f"--tolerance-db takes a number >= 0, got {args.tolerance_db}")


def write_run_cost(run_dir: str | Path) -> Path:
    """``RUN_DIR/cost.json``: the report ``dronecap cost RUN_DIR`` gives with its defaults
    (the train command calls this: the NeRF core never imports the cost model)."""
    from dronecap.files import atomic_output
    from dronecap.gap9.model import cost_report, deployed
    from dronecap.nerf.run_dir import COST, read_resolved

    rep = cost_report(deployed(read_resolved(run_dir).config))
    out = Path(run_dir) / COST
    with atomic_output(out) as tmp:
        tmp.write_text(json.dumps(rep, indent=1))
    return out


def _bytes(text: str | None, flag: str) -> int | None:
    from dronecap.errors import InputError
    from dronecap.gap9.platform import parse_bytes

    if text is None:
        return None
    try:
        return parse_bytes(text)
    except ValueError as err:
        raise InputError(f"{flag}: {err}") from err


def _report(args: Settings) -> int:
    from dronecap.errors import InputError
    from dronecap.files import atomic_output
    from dronecap.gap9.model import cost_report, format_report

    cfg, default_out = _config(args)
    try:
        rep = cost_report(cfg, _platform(args), samples_per_pixel=args.spp, n_images=args.images)
    except (ValueError, ZeroDivisionError) as err:
        raise InputError(f"impossible configuration: {err}") from err
    print(format_report(rep))
    out = Path(args.json) if args.json else default_out
    with atomic_output(out) as tmp:
        tmp.write_text(json.dumps(rep, indent=1))
    print(f"wrote {out}")
    return 0


def _table2(args: Settings) -> int:
    from dronecap.gap9.paper import table2

    rows = table2(_platform(args))
    head = f"{'Mem paper':>9} {'model':>7} {'err':>7}"
    print(f"{'row':<12} {head}   {head.replace('Mem', 'GOp')}")
    for r in rows:
        print(
            f"{r['name']:<12} {r['mem_paper']:>9.0f} {r['mem_model']:>7.1f} {r['mem_err']:>+7.1%}"
            f"   {r['gop_paper']:>9.2f} {r['gop_model']:>7.3f} {r['gop_err']:>+7.1%}"
        )
    worst_m = max(abs(r["mem_err"]) for r in rows)
    worst_g = max(abs(r["gop_err"]) for r in rows)
    print(f"worst |error|: memory {worst_m:.1%}, compute {worst_g:.1%} (MB = 1e6 B, GOp = 1e9 op)")
    return 0


def _search(args: Settings) -> int:
    from dronecap import workspace
    from dronecap.errors import InputError
    from dronecap.gap9.search import (
        Budget,
        choose,
        evaluate,
        load_runs,
        paper_points,
        pareto_plot,
        search,
    )

    budget = Budget(
        l3=_bytes(args.budget_l3, "--budget-l3"),
        l2=_bytes(args.budget_l2, "--budget-l2"),
        l1=_bytes(args.budget_l1, "--budget-l1"),
    )
    if budget.l3 is None and budget.l2 is None and budget.l1 is None:
        raise InputError("--search needs at least one of --budget-l3/--budget-l2/--budget-l1")
    if args.runs:
        try:
            points = load_runs(args.runs)
        except ValueError as err:
            raise InputError(str(err)) from err
        title = "measured runs"
    else:
        points = paper_points()
        title = "the paper's Table II PSNRs (published, not measured here)"
    platform = _platform(args)
    fits = search(budget, platform)
    print(f"{len(fits)} configurations fit; the {min(args.top, len(fits))} smallest:")
    print(f"{'B':>6} {'log2T':>5} {'res':>4} {'grid':>4} {'hid':>4} {'L':>3} "
          f"{'Mem MB':>7} {'L2 kB':>7} {'GOp':>6} {'train min':>9}")  # fmt: skip
    for r in fits[: args.top]:
        print(
            f"{r['batch_samples']:>6} {r['log2_hashmap']:>5} {r['resolution']:>4} "
            f"{r['grid_res']:>4} {r['hidden']:>4} {r['levels']:>3} {r['mem_mb']:>7.2f} "
            f"{r['l2_kb']:>7.0f} {r['gop']:>6.3f} {r['train_min']:>9.1f}"
        )
    evaluate(points, budget, platform)
    chosen = choose(points, args.tolerance_db)
    out = Path(args.plot) if args.plot else workspace.resolve(args.workdir, None, "pareto.png")
    budget_mb = None if budget.l3 is None else budget.l3 / 1e6
    drawn = pareto_plot(points, chosen, out, budget_mb, f"memory vs PSNR: {title}")
    if chosen is None:
        print(f"no {'run' if args.runs else 'Table II row'} fits the budget")
    else:
        print(f"chosen: {chosen.label} ({chosen.mem_mb:.1f} MB, {chosen.psnr:.2f} dB; {title})")
    if drawn is not None:
        print(f"wrote {drawn}")
    return 0


def run(args: Settings) -> int:
    """Print the report (or the Table II comparison, or the search) and write its outputs."""
    _check_options(args)
    if args.table2:
        return _table2(args)
    if args.search:
        return _search(args)
    return _report(args)
