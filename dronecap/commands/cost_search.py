"""The two other faces of ``dronecap cost`` (its settings are :class:`commands.cost.Settings`):
``--table2`` (the model against the paper's Table II) and ``--search`` (configurations fitting
memory budgets, the chosen one, the Pareto picture)."""

from __future__ import annotations

from pathlib import Path

from dronecap.commands.cost import Settings, platform


def table2(args: Settings) -> int:
    """``dronecap cost --table2``: the model against the paper's Table II, row by row."""
    from dronecap.gap9.paper import table2 as paper_table2

    rows = paper_table2(platform(args))
    head = f"{'Mem paper':>9} {'model':>7} {'err':>7} {'>round':>7}"
    print(f"{'row':<12} {head}   {'GOp paper':>9} {'model':>7} {'err':>7}")
    for r in rows:
        print(
            f"{r['name']:<12} {r['mem_paper']:>9.0f} {r['mem_model']:>7.1f} {r['mem_err']:>+7.1%}"
            f" {r['mem_err_rounding']:>+7.1%}"
            f"   {r['gop_paper']:>9.2f} {r['gop_model']:>7.3f} {r['gop_err']:>+7.1%}"
        )
    worst_m = max(abs(r["mem_err"]) for r in rows)
    worst_r = max(abs(r["mem_err_rounding"]) for r in rows)
    worst_g = max(abs(r["gop_err"]) for r in rows)
    print(
        f"worst |error|: memory {worst_m:.1%} ({worst_r:.1%} beyond the paper's whole-MB "
        f"rounding), compute {worst_g:.1%} (MB = 1e6 B, GOp = 1e9 op)"
    )
    return 0


def search(args: Settings) -> int:
    """``dronecap cost --search``: the configurations fitting the budgets, the chosen one, the
    Pareto picture."""
    from dronecap import workspace
    from dronecap.errors import InputError
    from dronecap.gap9.search import (
        Budget,
        choose,
        evaluate,
        load_runs,
        paper_points,
        pareto_plot,
    )
    from dronecap.gap9.search import search as search_budget

    budget = Budget(l3=args.budget_l3, l2=args.budget_l2, l1=args.budget_l1)
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
    target = platform(args)
    fits = search_budget(budget, target)
    print(f"{len(fits)} configurations fit; the {min(args.top, len(fits))} smallest:")
    print(f"{'B':>6} {'log2T':>5} {'res':>4} {'grid':>4} {'hid':>4} {'L':>3} "
          f"{'Mem MB':>7} {'L2 kB':>7} {'GOp':>6} {'train min':>9}")  # fmt: skip
    for r in fits[: args.top]:
        print(
            f"{r['batch_samples']:>6} {r['log2_hashmap']:>5} {r['resolution']:>4} "
            f"{r['grid_res']:>4} {r['hidden']:>4} {r['levels']:>3} {r['mem_mb']:>7.2f} "
            f"{r['l2_kb']:>7.0f} {r['gop']:>6.3f} {r['train_min']:>9.1f}"
        )
    evaluate(points, budget, target)
    chosen = choose(points, args.tolerance_db)
    out = Path(args.plot) if args.plot else workspace.resolve(args.workdir, None, workspace.PARETO)
    budget_mb = None if budget.l3 is None else budget.l3 / 1e6
    drawn = pareto_plot(points, chosen, out, budget_mb, f"memory vs PSNR: {title}")
    if chosen is None:
        print(f"no {'run' if args.runs else 'Table II row'} fits the budget")
    else:
        print(f"chosen: {chosen.label} ({chosen.mem_mb:.1f} MB, {chosen.psnr:.2f} dB; {title})")
    if drawn is not None:
        print(f"wrote {drawn}")
    if args.target_psnr is not None:
        _print_to_target(points, args.target_psnr, target, title, args.grid_rule)
    return 0


def _print_to_target(points: list, target_db: float, target, title: str, grid_rule: str) -> None:
    """The points ranked by modelled GAP9 energy to ``target_db`` (cheapest first), their
    grids updated by ``grid_rule``."""
    from dronecap.gap9.energy import assumptions
    from dronecap.gap9.search import to_target

    print(f"to {target_db:g} dB on {target.name} ({title}; {grid_rule} grid rule), "
          "cheapest energy first:")  # fmt: skip
    print(f"{'run':<20} {'steps':>6} {'GAP9 min':>9} {'energy J':>9} {'Mem MB':>7} "
          f"{'trained':>7} {'hull':>5}")  # fmt: skip
    for r in to_target(points, target_db, target, grid_rule):
        shares = f"{r['trained']:>7.2f} {r['hull']:>5.2f}"
        if r["steps"] is None:
            print(f"{r['label']:<20} {'never reached':>26} {r['mem_mb']:>7.1f} {shares}")
        else:
            print(
                f"{r['label']:<20} {r['steps']:>6} {r['minutes']:>9.1f} {r['joules']:>9.1f} "
                f"{r['mem_mb']:>7.1f} {shares}"
            )
    for name, text in assumptions(target).items():
        print(f"  {name}: {text}")
