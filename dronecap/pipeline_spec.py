"""Reading and validating ``pipelines.yaml`` before anything runs.

A pipeline is an ordered mapping of stages. A stage names a ``dronecap`` command (the stage id
by default) and its parameters, with exactly the names of that command's CLI options (dashes or
underscores), checked against the command's settings dataclass (:mod:`dronecap.settings`): name,
type and choices. String values may use ``${var}`` for a pipeline variable and ``${stage}`` for the
output folder of an earlier stage, which also makes that stage an upstream dependency::

    demo:
      vars: {frames: 240}
      stages:
        simulate: {params: {scene: corridor, frames: "${frames}"}}
        ingest:   {params: {video: "${simulate}/flight.mp4"}}

Every problem (unknown pipeline, stage or parameter, wrong type, reference to a later or missing
stage, cycle) raises :class:`SpecError` naming the file and the line that is wrong.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from dronecap.errors import InputError
from dronecap.registry import STAGES
from dronecap.settings_cli import missing_params, param_value, params_table

REF = re.compile(r"\$\{([A-Za-z0-9_.-]+)\}")
# Pipeline and stage names become folders under the runs folder: letters, digits, '_' and '-'
# only (no path separator, no '.', '..', absolute path or hidden name), at most 64 characters.
NAME = re.compile(r"[A-Za-z0-9_][A-Za-z0-9_-]{0,63}")


class SpecError(InputError):
    """A malformed pipelines.yaml; the message carries ``file:line``."""


def check_name(kind: str, name: object, at: str) -> str:
    """``name`` when it is a safe folder name (:data:`NAME`); SpecError at ``at`` otherwise."""
    if not isinstance(name, str) or not NAME.fullmatch(name):
        raise SpecError(
            f"{at}: {kind} name {name!r} is not allowed: use letters, digits, '_' and '-' only "
            "(it names a folder under the runs folder)"
        )
    return name


class _LineLoader(yaml.SafeLoader):
    """SafeLoader whose mappings remember the line of each key (``_lines``, 1-based)."""


class LineDict(dict):
    """A dict from YAML with the source line of the mapping and of each key."""

    line: int = 0
    key_lines: dict[str, int]


def _construct_mapping(loader: _LineLoader, node: yaml.MappingNode) -> LineDict:
    d = LineDict()
    d.line = node.start_mark.line + 1
    d.key_lines = {}
    for key_node, value_node in node.value:
        key = loader.construct_object(key_node, deep=True)
        d[key] = loader.construct_object(value_node, deep=True)
        d.key_lines[key] = key_node.start_mark.line + 1
    return d


_LineLoader.add_constructor(yaml.resolver.BaseResolver.DEFAULT_MAPPING_TAG, _construct_mapping)


@dataclass
class PipelineStage:
    """One use of a stage in a pipeline, after validation: its id, the command (a
    :data:`dronecap.stages.STAGES` entry, :class:`dronecap.registry.Stage`) and its parameters."""

    id: str
    command: str
    params: dict[str, Any]  # parameter (option name) -> value, ${...} not yet substituted
    line: int  # line of the stage in the YAML file
    param_lines: dict[str, int] = field(default_factory=dict)
    upstream: list[str] = field(default_factory=list)  # ids of stages it reads from


@dataclass
class Pipeline:
    """A named, validated pipeline: stages in execution order and its variables."""

    name: str
    stages: list[PipelineStage]
    vars: dict[str, Any]
    description: str = ""

    def stage(self, stage_id: str) -> PipelineStage:
        """The stage with this id (SpecError listing the ids when unknown)."""
        for s in self.stages:
            if s.id == stage_id:
                return s
        raise SpecError(f"no stage {stage_id!r} in pipeline {self.name!r}; stages: {self.ids()}")

    def ids(self) -> list[str]:
        """Stage ids in execution order."""
        return [s.id for s in self.stages]


def load_specs(path: str | Path) -> LineDict:
    """Parse the YAML file (line-aware), refusing anything but a mapping of pipelines."""
    path = Path(path)
    if not path.exists():
        raise SpecError("no such file", path)
    try:
        data = yaml.load(path.read_text(), Loader=_LineLoader)  # noqa: S506 (SafeLoader subclass)
    except yaml.YAMLError as err:
        mark = getattr(err, "problem_mark", None)
        where = f"{path}:{mark.line + 1}" if mark else str(path)
        problem = str(getattr(err, "problem", err))
        tag = re.search(r"for the tag '(?:tag:yaml.org,2002:)?([^']*)'", problem)
        if tag:
            problem = f"the tag !!{tag.group(1)} is not allowed: plain data only (nothing was run)"
        raise SpecError(f"{where}: invalid YAML: {problem}") from None
    if not isinstance(data, dict):
        raise SpecError(f"{path}:1: expected a mapping of pipeline names to pipelines")
    return data


def parse_overrides(items: list[str]) -> tuple[dict[str, Any], dict[str, dict[str, Any]]]:
    """Split ``key=value`` overrides into pipeline vars and ``stage.param`` overrides.

    Values are parsed as YAML scalars (``2000`` -> int, ``true`` -> bool, ``a.mp4`` -> str).
    """
    vars_: dict[str, Any] = {}
    stage_params: dict[str, dict[str, Any]] = {}
    for item in items:
        if "=" not in item:
            raise SpecError(f"override {item!r} is not of the form key=value or stage.param=value")
        key, raw = item.split("=", 1)
        value = yaml.safe_load(raw) if raw else ""
        if "." in key:
            stage_id, param = key.split(".", 1)
            stage_params.setdefault(stage_id, {})[param.replace("-", "_")] = value
        else:
            vars_[key] = value
    return vars_, stage_params


def build_pipeline(
    specs: LineDict,
    name: str,
    path: str | Path,
    overrides: list[str] | None = None,
) -> Pipeline:
    """Validate pipeline ``name`` against the commands' settings and apply overrides.

    Args:
        specs: the parsed file from :func:`load_specs`.
        name: pipeline to build.
        path: the YAML file, for messages.
        overrides: ``key=value`` items from the command line.
    """
    if name not in specs:
        raise SpecError(f"{path}: no pipeline {name!r}; pipelines: {', '.join(specs)}")
    spec = specs[name]
    at = f"{path}:{specs.key_lines[name]}"
    check_name("pipeline", name, at)
    if not isinstance(spec, dict) or not isinstance(spec.get("stages"), dict):
        raise SpecError(f"{at}: pipeline {name!r} needs a 'stages' mapping")
    for key in spec:
        if key not in ("stages", "vars", "description"):
            raise SpecError(f"{path}:{spec.key_lines[key]}: unknown pipeline key {key!r}")
    var_overrides, param_overrides = parse_overrides(overrides or [])
    vars_ = dict(spec.get("vars") or {})
    for key in var_overrides:
        if key not in vars_:
            raise SpecError(f"{at}: pipeline {name!r} has no variable {key!r}; vars: {list(vars_)}")
    vars_.update(var_overrides)
    stages_spec: LineDict = spec["stages"]
    for stage_id in stages_spec:
        check_name("stage", stage_id, f"{path}:{stages_spec.key_lines[stage_id]}")
    for stage_id in param_overrides:
        if stage_id not in stages_spec:
            raise SpecError(f"{at}: override names unknown stage {stage_id!r}")

    stages: list[PipelineStage] = []
    for stage_id, body in stages_spec.items():
        line = stages_spec.key_lines[stage_id]
        body = body if body is not None else LineDict()
        if not isinstance(body, dict):
            raise SpecError(f"{path}:{line}: stage {stage_id!r} must be a mapping")
        if stage_id in vars_:
            raise SpecError(f"{path}:{line}: stage {stage_id!r} has the name of a variable")
        for key in body:
            if key not in ("command", "params"):
                raise SpecError(f"{path}:{body.key_lines[key]}: unknown stage key {key!r}")
        command = body.get("command", stage_id)
        if command not in STAGES or not STAGES[command].pipeline:
            raise SpecError(f"{path}:{line}: unknown stage command {command!r}")
        params_node = body.get("params") or LineDict()
        param_lines = dict(getattr(params_node, "key_lines", {}))
        params = {str(k).replace("-", "_"): v for k, v in params_node.items()}
        param_lines = {str(k).replace("-", "_"): v for k, v in param_lines.items()}
        for k, v in param_overrides.get(stage_id, {}).items():
            params[k] = v
            param_lines.setdefault(k, line)
        stage = PipelineStage(stage_id, command, params, line, param_lines)
        _check_params(stage, STAGES[command].load()[0], path)
        _check_refs(stage, vars_, [s.id for s in stages], list(stages_spec), path)
        stages.append(stage)
    return Pipeline(name, stages, vars_, str(spec.get("description", "")))


def _check_params(stage: PipelineStage, settings_cls: type, path: str | Path) -> None:
    table = params_table(settings_cls)
    for key, value in stage.params.items():
        line = stage.param_lines.get(key, stage.line)
        if key not in table:
            known = ", ".join(sorted(table))
            raise SpecError(
                f"{path}:{line}: stage {stage.id!r}: unknown parameter {key!r} for"
                f" `dronecap {stage.command}` (known: {known})"
            )
        if isinstance(value, str) and REF.search(value):
            continue  # checked once substituted
        try:
            param_value(table[key], value)
        except ValueError as err:
            raise SpecError(
                f"{path}:{line}: parameter {key!r} of stage {stage.id!r} {err}"
            ) from None
    missing = missing_params(settings_cls, set(stage.params))
    if missing:
        raise SpecError(
            f"{path}:{stage.line}: stage {stage.id!r} needs parameter {missing[0]!r} for"
            f" `dronecap {stage.command}`"
        )


def _check_refs(
    stage: PipelineStage,
    vars_: dict[str, Any],
    earlier: list[str],
    all_ids: list[str],
    path: str | Path,
) -> None:
    for key, value in stage.params.items():
        for v in value if isinstance(value, list) else [value]:
            if not isinstance(v, str):
                continue
            for ref in REF.findall(v):
                line = stage.param_lines.get(key, stage.line)
                if ref in vars_:
                    continue
                if ref in earlier:
                    if ref not in stage.upstream:
                        stage.upstream.append(ref)
                    continue
                if ref == stage.id or ref in all_ids:
                    raise SpecError(
                        f"{path}:{line}: stage {stage.id!r} reads from {ref!r}, which runs"
                        " at or after it (a cycle or wrong order)"
                    )
                raise SpecError(f"{path}:{line}: unknown variable or stage ${{{ref}}}")


def substitute(value: Any, vars_: dict[str, Any], stage_dirs: dict[str, Path]) -> Any:
    """Replace ``${var}`` and ``${stage}`` in strings (recursively in lists).

    A string that is exactly ``${var}`` keeps the variable's type (an int stays an int).
    """
    if isinstance(value, list):
        return [substitute(v, vars_, stage_dirs) for v in value]
    if not isinstance(value, str):
        return value
    whole = REF.fullmatch(value)
    if whole and whole.group(1) in vars_:
        return substitute(vars_[whole.group(1)], vars_, stage_dirs)

    def one(m: re.Match[str]) -> str:
        ref = m.group(1)
        return str(stage_dirs[ref]) if ref in stage_dirs else str(vars_[ref])

    return REF.sub(one, value)
