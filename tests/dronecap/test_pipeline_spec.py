"""pipelines.yaml validation: a malformed file is refused before anything runs, with its line."""

from __future__ import annotations

from pathlib import Path

import pytest

from dronecap.pipeline_spec import (
    SpecError,
    build_pipeline,
    load_specs,
    parse_overrides,
    substitute,
)


def _build(tmp_path: Path, text: str, overrides: list[str] | None = None):
    path = tmp_path / "pipelines.yaml"
    path.write_text(text)
    return build_pipeline(load_specs(path), "p", path, overrides)


GOOD = """\
p:
  vars: {scene: /data/lego, res: 80}
  stages:
    imp:
      command: import-blender
      params: {scene_dir: "${scene}", resolution: "${res}", color: gray}
    again:
      command: import-blender
      params:
        scene_dir: "${imp}/x"
"""


def test_good_pipeline_resolves_vars_and_upstream(tmp_path: Path) -> None:
    p = _build(tmp_path, GOOD, ["res=40", "imp.color=rgb"])
    assert p.ids() == ["imp", "again"]
    assert p.stage("again").upstream == ["imp"]
    assert p.vars["res"] == 40  # override parsed as a YAML int
    assert p.stage("imp").params["color"] == "rgb"
    dirs = {"imp": Path("runs/p/imp")}
    # a whole-string reference keeps the variable's type
    assert substitute(p.stage("imp").params["resolution"], p.vars, dirs) == 40
    assert substitute(p.stage("again").params["scene_dir"], p.vars, dirs) == "runs/p/imp/x"


@pytest.mark.parametrize(
    ("text", "line", "words"),
    [
        # unknown stage command, on line 4
        (
            "p:\n  stages:\n    a: {command: import-blender, params: {scene_dir: x}}\n    b: {}\n",
            4,
            "unknown stage command 'b'",
        ),
        # unknown parameter, on its own line (5)
        (
            "p:\n  stages:\n    a:\n      command: import-blender\n      params: {colour: rgb}\n",
            5,
            "unknown parameter 'colour'",
        ),
        # wrong type
        (
            "p:\n  stages:\n    a:\n      command: import-blender\n      params:\n"
            "        scene_dir: x\n        resolution: big\n",
            7,
            "must be int",
        ),
        # a choice outside the allowed ones
        (
            "p:\n  stages:\n    a:\n      command: import-blender\n      params:\n"
            "        color: blue\n",
            6,
            "must be one of",
        ),
        # reading from a later stage (or itself): a cycle / wrong order
        (
            "p:\n  stages:\n    a:\n      command: import-blender\n      params:\n"
            "        scene_dir: ${b}/x\n    b:\n      command: import-blender\n",
            6,
            "cycle",
        ),
        (
            "p:\n  stages:\n    a:\n      command: import-blender\n      params:\n"
            "        scene_dir: ${a}/x\n",
            6,
            "cycle",
        ),
        # unknown variable
        (
            "p:\n  stages:\n    a:\n      command: import-blender\n      params:\n"
            "        scene_dir: ${nowhere}\n",
            6,
            "unknown variable or stage",
        ),
        # unknown key in a stage
        (
            "p:\n  stages:\n    a:\n      command: import-blender\n      paramz: {}\n",
            5,
            "unknown stage key",
        ),
        # broken YAML syntax
        ("p:\n  stages:\n    a: [unclosed\n", 4, "invalid YAML"),
    ],
)
def test_malformed_files_are_refused_with_their_line(
    tmp_path: Path, text: str, line: int, words: str
) -> None:
    with pytest.raises(SpecError) as err:
        _build(tmp_path, text)
    msg = str(err.value)
    assert f"pipelines.yaml:{line}" in msg, msg
    assert words in msg
    assert "\n" not in msg


def test_unknown_pipeline_and_bad_overrides(tmp_path: Path) -> None:
    with pytest.raises(SpecError, match="no pipeline 'q'"):
        path = tmp_path / "pipelines.yaml"
        path.write_text(GOOD)
        build_pipeline(load_specs(path), "q", path)
    with pytest.raises(SpecError, match="no variable 'nope'"):
        _build(tmp_path, GOOD, ["nope=1"])
    with pytest.raises(SpecError, match="unknown stage 'zz'"):
        _build(tmp_path, GOOD, ["zz.steps=3"])
    with pytest.raises(SpecError, match="key=value"):
        parse_overrides(["steps"])


def test_shipped_pipelines_file_is_valid() -> None:
    """Every pipeline in the repo's pipelines.yaml validates against the commands' settings."""
    path = Path(__file__).resolve().parents[2] / "pipelines.yaml"
    specs = load_specs(path)
    for name in specs:
        assert build_pipeline(specs, name, path).stages
