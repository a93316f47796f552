"""The pipeline runner: run a validated pipeline's stages in order, with caching.

Each stage runs the ``dronecap`` command it names, in-process: its parameters become the
command's settings (:func:`dronecap.settings_cli.from_params`) with the workspace
``runs/<pipeline>/<stage>``, so that its outputs land in its own folder, and the command's
``run`` is called with them (:func:`dronecap.cli.call`). Beside them the runner
keeps a stamp, ``.dronecap-stage.json``: the cache key (a hash of the parameters and of the
content of every input file), the parameters, the inputs' hashes, the time taken and the key
figure. A stage is skipped when its key matches a completed stamp, like ``dvc repro``.

A stage that was interrupted leaves a "running" stamp with its key: run again with the same
key, it keeps its folder so that a resumable command (``train``) continues from its checkpoint;
with another key the folder is cleared first. Parameters that only say how to compute
(:data:`RESOURCE_PARAMS`: threads, progress output) are not part of the key, and a parameter
that only extends the work (the registry's ``extends``: more training ``steps``) keeps the
folder, so the trainer resumes from its checkpoint instead of starting over.
"""

from __future__ import annotations

import hashlib
import json
import shutil
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from dronecap.errors import InputError
from dronecap.files import atomic_output, output_lock, sha256_file
from dronecap.pipeline_spec import Pipeline, PipelineStage, substitute
from dronecap.registry import STAGES

STAMP = ".dronecap-stage.json"
# Parameters that change how a stage computes, not what it computes: never part of the cache key.
RESOURCE_PARAMS = frozenset({"threads", "no_progress", "quiet", "checkpoint_every"})


@dataclass
class StageResult:
    """What happened to one stage."""

    id: str
    status: str  # "ran", "cached", "would run", "failed", "skipped"
    why: str
    seconds: float = 0.0
    figure: str = ""


def input_files(params: dict[str, Any]) -> list[Path]:
    """Parameter values that name an existing file or folder: the stage's inputs."""
    found: list[Path] = []
    for value in params.values():
        for v in value if isinstance(value, list) else [value]:
            if isinstance(v, str) and v and Path(v).exists():
                found.append(Path(v))
    return found


def cache_key(command: str, params: dict[str, Any], hashes: dict[str, str]) -> str:
    """Hash of what determines a stage's output: its parameters (less the resource ones) and its
    inputs' contents."""
    kept = {k: v for k, v in params.items() if k not in RESOURCE_PARAMS}
    blob = json.dumps({"command": command, "params": kept, "inputs": hashes}, sort_keys=True)
    return hashlib.sha256(blob.encode()).hexdigest()


def _changed(old: dict[str, Any], new: dict[str, Any]) -> list[str]:
    """Parameters (less the resource ones) whose values differ between two runs."""
    keys = (set(old) | set(new)) - RESOURCE_PARAMS
    return sorted(k for k in keys if old.get(k) != new.get(k))


def read_stamp(stage_dir: Path) -> dict[str, Any] | None:
    """The stamp left by an earlier run of a stage, or None."""
    try:
        return json.loads((stage_dir / STAMP).read_text())
    except (FileNotFoundError, json.JSONDecodeError):
        return None


def _write_stamp(stage_dir: Path, stamp: dict[str, Any]) -> None:
    with atomic_output(stage_dir / STAMP) as tmp:
        tmp.write_text(json.dumps(stamp, indent=2))


class Runner:
    """Runs one pipeline under ``root/<pipeline>/`` (``root`` defaults to ``runs``)."""

    def __init__(
        self,
        pipeline: Pipeline,
        root: Path = Path("runs"),
        force: set[str] | None = None,
        start: str | None = None,
        until: str | None = None,
    ) -> None:
        self.pipeline = pipeline
        self.dir = root / pipeline.name
        self.force = set(force or ())
        ids = pipeline.ids()
        for sid in self.force | {s for s in (start, until) if s}:
            pipeline.stage(sid)  # raises with the known ids
        self.first = ids.index(start) if start else 0
        self.last = ids.index(until) if until else len(ids) - 1
        self.stage_dirs = {sid: self.dir / sid for sid in ids}
        inside = root.resolve()
        for d in (self.dir, *self.stage_dirs.values()):
            if d.is_symlink() or not d.resolve().is_relative_to(inside):
                raise InputError(f"is a link or leaves the runs folder {root}: not using it", d)

    def _plan(self, stage: PipelineStage) -> tuple[dict[str, Any], dict[str, str], str]:
        params = {
            k: substitute(v, self.pipeline.vars, self.stage_dirs) for k, v in stage.params.items()
        }
        hashes = {str(p): sha256_file(p) for p in input_files(params)}
        folder = STAGES[stage.command].folder
        if folder and folder not in params:
            params[folder] = str(self.stage_dirs[stage.id])
        return params, hashes, cache_key(stage.command, params, hashes)

    def _why(
        self,
        stage: PipelineStage,
        stamp: dict[str, Any] | None,
        params: dict,
        hashes: dict,
        key: str,
    ) -> str:
        if stage.id in self.force:
            return "forced"
        if stamp is None:
            return "no previous output"
        if stamp.get("status") != "done":
            if stamp.get("key") == key:
                return "previous run did not finish (resuming)"
            return "previous run did not finish, with other inputs (starting over)"
        changed = _changed(stamp.get("params", {}), params)
        if changed:
            old, new = stamp.get("params", {}), params
            diff = ", ".join(f"{k}: {old.get(k)} -> {new.get(k)}" for k in changed)
            return f"parameters changed ({diff})"
        changed = [p for p, h in hashes.items() if stamp.get("inputs", {}).get(p) != h]
        return f"input changed: {', '.join(changed)}" if changed else "up to date"

    def _keeps_folder(
        self, stage: PipelineStage, stamp: dict[str, Any] | None, params: dict, key: str
    ):
        """True when the stage's folder is resumed, not cleared: an interrupted run with the same
        key, or a finished one whose only change extends it (more steps) with the same inputs."""
        if stamp is None or stage.id in self.force:
            return False
        if stamp.get("status") != "done":
            return stamp.get("key") == key
        changed = set(_changed(stamp.get("params", {}), params))
        return bool(changed) and changed <= STAGES[stage.command].extends

    def run(self, dry_run: bool = False) -> list[StageResult]:
        """Run (or with ``dry_run`` only explain) the stages; stops at the first failure. The
        pipeline's folder is locked meanwhile: a second run of it stops (or waits) at once."""
        if dry_run:
            return self._run(dry_run)
        with output_lock(self.dir):
            return self._run(dry_run)

    def _run(self, dry_run: bool) -> list[StageResult]:
        from dronecap.cli import call
        from dronecap.figures import key_figure
        from dronecap.settings_cli import command_line, from_params

        results: list[StageResult] = []
        upstream_runs: set[str] = set()
        for i, stage in enumerate(self.pipeline.stages):
            sdir = self.stage_dirs[stage.id]
            stamp = read_stamp(sdir)
            if i > self.last:
                results.append(StageResult(stage.id, "skipped", "after --until"))
                continue
            pending = [u for u in stage.upstream if u in upstream_runs]
            if dry_run and pending:
                results.append(StageResult(stage.id, "would run", f"upstream {pending[0]} runs"))
                upstream_runs.add(stage.id)
                continue
            params, hashes, key = self._plan(stage)
            why = self._why(stage, stamp, params, hashes, key)
            if i < self.first:
                if why != "up to date":
                    raise InputError(
                        f"stage {stage.id!r} comes before --from and is not up to date ({why})"
                    )
                results.append(
                    StageResult(stage.id, "cached", "before --from", figure=stamp.get("figure", ""))
                )
                continue
            if why == "up to date":
                results.append(
                    StageResult(
                        stage.id, "cached", why, stamp.get("seconds", 0.0), stamp.get("figure", "")
                    )
                )
                continue
            upstream_runs.add(stage.id)
            if dry_run:
                results.append(StageResult(stage.id, "would run", why))
                continue
            entry = STAGES[stage.command]
            try:
                settings = from_params(entry.load()[0], params, str(sdir))
            except InputError as err:
                print(f"dronecap {stage.command}: error: {err}", file=sys.stderr)
                results.append(StageResult(stage.id, "failed", str(err)))
                break
            argv = command_line(settings)
            same_inputs = stamp is not None and stamp.get("inputs") == hashes
            resuming = same_inputs and self._keeps_folder(stage, stamp, params, key)
            if sdir.exists() and not resuming:
                shutil.rmtree(sdir)
            sdir.mkdir(parents=True, exist_ok=True)
            record = {
                "key": key,
                "status": "running",
                "command": stage.command,
                "params": params,
                "argv": argv,
                "inputs": hashes,
            }
            _write_stamp(sdir, record)
            full = [stage.command, *argv, "--workdir", str(sdir)]
            print(f"\n== stage {stage.id}: dronecap {' '.join(full)}", flush=True)
            t0 = time.perf_counter()
            code = call(entry, lambda _, s=settings: s)
            seconds = time.perf_counter() - t0
            if code != 0:
                results.append(StageResult(stage.id, "failed", f"exit code {code}", seconds))
                break
            figure = key_figure(entry.figure, sdir)
            _write_stamp(sdir, {**record, "status": "done", "seconds": seconds, "figure": figure})
            results.append(StageResult(stage.id, "ran", why, seconds, figure))
        return results


def summary_table(results: list[StageResult]) -> str:
    """A plain-text table: stage, ran/cached, time, key figure, reason."""
    rows = [("stage", "status", "time", "key figure", "why")]
    rows += [(r.id, r.status, f"{r.seconds:.1f} s", r.figure, r.why) for r in results]
    widths = [max(len(row[c]) for row in rows) for c in range(5)]
    lines = [
        "  ".join(cell.ljust(w) for cell, w in zip(row, widths, strict=True)).rstrip()
        for row in rows
    ]
    lines.insert(1, "  ".join("-" * w for w in widths))
    return "\n".join(lines)


def write_report(runner: Runner, results: list[StageResult]) -> Path:
    """``runs/<pipeline>/report.md`` and the self-contained ``report.html``: the summary table and
    every stage's pictures (made under ``runs/<pipeline>/pictures/``); returns the HTML path."""
    from dronecap.report_html import PICTURES, stage_pictures, write_html

    pictures: dict[str, list[Path]] = {}
    for r in results:
        stage, sdir = runner.pipeline.stage(r.id), runner.stage_dirs[r.id]
        stamp = read_stamp(sdir) or {}
        if stamp.get("status") == "done":
            pics = stage_pictures(
                stage.command, sdir, stamp.get("params", {}), runner.dir / PICTURES
            )
            pictures[r.id] = pics
    lines = [f"# Pipeline `{runner.pipeline.name}`", ""]
    if runner.pipeline.description:
        lines += [runner.pipeline.description, ""]
    lines += ["| stage | status | time | key figure |", "|---|---|---|---|"]
    lines += [f"| {r.id} | {r.status} | {r.seconds:.1f} s | {r.figure} |" for r in results]
    for sid, pics in pictures.items():
        if pics:
            lines += ["", f"## {sid}", ""]
            lines += [f"![{p.name}]({p.relative_to(runner.dir)})" for p in pics]
    runner.dir.mkdir(parents=True, exist_ok=True)
    with atomic_output(runner.dir / "report.md") as tmp:
        tmp.write_text("\n".join(lines) + "\n")
    rows = [("stage", "status", "time", "key figure", "why")]
    rows += [(r.id, r.status, f"{r.seconds:.1f} s", r.figure, r.why) for r in results]
    title = f"dronecap pipeline {runner.pipeline.name}"
    return write_html(
        runner.dir / "report.html", title, runner.pipeline.description, rows, pictures
    )
