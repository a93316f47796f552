"""`dronecap run NAME [key=value ...]`: run a pipeline from pipelines.yaml with caching."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from dronecap.settings import Settings as Base
from dronecap.settings import setting


@dataclass(kw_only=True)
class Settings(Base):
    """Options of ``dronecap run``."""

    name: str | None = setting(
        None, positional=True, help="pipeline name (omit to list the pipelines)"
    )
    overrides: list[str] = setting(
        factory=list,
        positional=True,
        help="pipeline variables (video=my.mp4) or stage parameters (train.steps=2000)",
    )
    file: str | None = setting(None, help="pipelines file (default: pipelines.yaml here)")
    runs: str | None = setting(None, help="root of the stage outputs (default: WORKDIR/runs)")
    force: list[str] = setting(factory=list, repeat=True, metavar="STAGE", help="re-run STAGE")
    dry_run: bool = setting(False, help="say what would run and why, run nothing")
    start: str | None = setting(
        None, flag="--from", metavar="STAGE", help="start at STAGE (earlier ones must be cached)"
    )
    until: str | None = setting(None, metavar="STAGE", help="stop after STAGE")


def _pipelines_file(args: Settings) -> Path:
    if args.file:
        return Path(args.file)
    here = Path(args.workdir) / "pipelines.yaml"
    if here.exists():
        return here
    # The file shipped with dronecap (package data; the repo root's pipelines.yaml links to it).
    from importlib.resources import files

    return Path(str(files("dronecap") / "pipelines.yaml"))


def run(args: Settings) -> int:
    """Validate the pipeline, run it, print the summary and write report.md."""
    from dronecap.figures import results_of
    from dronecap.pipeline import Runner, summary_table, write_report
    from dronecap.pipeline_spec import build_pipeline, load_specs

    path = _pipelines_file(args)
    specs = load_specs(path)
    if not args.name:
        for name, spec in specs.items():
            print(f"{name:20s} {spec.get('description', '') if isinstance(spec, dict) else ''}")
        return 0
    pipeline = build_pipeline(specs, args.name, path, args.overrides)
    root = Path(args.runs) if args.runs else Path(args.workdir) / "runs"
    runner = Runner(pipeline, root, set(args.force), args.start, args.until)
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
