"""`dronecap run NAME [key=value ...]`: run a pipeline from pipelines.yaml with caching."""

from __future__ import annotations

import argparse
from pathlib import Path

HELP = "run a pipeline from pipelines.yaml with caching"


def add_arguments(p: argparse.ArgumentParser) -> None:
    """Options of `dronecap run`."""
    p.add_argument("name", nargs="?", help="pipeline name (omit to list the pipelines)")
    p.add_argument(
        "overrides",
        nargs="*",
        metavar="key=value",
        help="pipeline variables (video=my.mp4) or stage parameters (train.steps=2000)",
    )
    p.add_argument("--file", default=None, help="pipelines file (default: pipelines.yaml here)")
    p.add_argument("--runs", default=None, help="root of the stage outputs (default: WORKDIR/runs)")
    p.add_argument("--force", action="append", default=[], metavar="STAGE", help="re-run STAGE")
    p.add_argument("--dry-run", action="store_true", help="say what would run and why, run nothing")
    p.add_argument(
        "--from", dest="start", metavar="STAGE", help="start at STAGE (earlier ones must be cached)"
    )
    p.add_argument("--until", metavar="STAGE", help="stop after STAGE")


def _pipelines_file(args: argparse.Namespace) -> Path:
    if args.file:
        return Path(args.file)
    here = Path(args.workdir) / "pipelines.yaml"
    if here.exists():
        return here
    # The file shipped with dronecap (package data; in the repo a link to the root's file).
    from importlib.resources import files

    return Path(str(files("dronecap") / "pipelines.yaml"))


def run(args: argparse.Namespace) -> int:
    """Validate the pipeline, run it, print the summary and write report.md."""
    from dronecap.cli import COMMANDS, build_parser
    from dronecap.figures import results_of
    from dronecap.pipeline import Runner, summary_table, write_report
    from dronecap.pipeline_spec import build_pipeline, commands_used, load_specs

    path = _pipelines_file(args)
    specs = load_specs(path)
    if not args.name:
        for name, spec in specs.items():
            print(f"{name:20s} {spec.get('description', '') if isinstance(spec, dict) else ''}")
        return 0
    # Only the commands this pipeline uses are imported (each parser import is light).
    parsers = {n: build_parser(n)[0] for n in commands_used(specs, args.name) if n in COMMANDS}
    pipeline = build_pipeline(specs, args.name, path, parsers, args.overrides)
    root = Path(args.runs) if args.runs else Path(args.workdir) / "runs"
    runner = Runner(pipeline, parsers, root, set(args.force), args.start, args.until)
    results = runner.run(dry_run=args.dry_run)
    print("\n" + summary_table(results))
    if args.dry_run:
        return 0
    report = write_report(runner, results)
    print(f"\nreport: {report}")
    for r in results:
        found = results_of(runner.stage_dirs[r.id])
        if found:
            print(f"{r.id}: {', '.join(str(p) for p in found)}")
    return 1 if any(r.status == "failed" for r in results) else 0
