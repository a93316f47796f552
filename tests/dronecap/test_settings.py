"""Stage contracts: options, pipeline parameters and the runner's calls all come from one
settings dataclass per stage."""

from __future__ import annotations

import argparse
import dataclasses
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest

from dronecap import cli
from dronecap.errors import InputError
from dronecap.pipeline import Runner
from dronecap.pipeline_spec import SpecError, build_pipeline, load_specs
from dronecap.registry import STAGES, Stage
from dronecap.settings import Settings, flatten, setting
from dronecap.settings_cli import (
    add_options,
    check,
    command_line,
    from_namespace,
    from_params,
    options,
)


@dataclass
class Knobs:
    """A domain dataclass exposed through :func:`flatten`."""

    depth: int = 3
    gain: float = 0.5


@dataclass(kw_only=True)
class Toy(Settings):
    """A stage's settings using every kind of setting."""

    source: str = setting(positional=True, help="input")
    count: int = setting(4, minimum=1, help="how many")
    mode: str = setting("fast", choices=("fast", "slow"), help="how")
    output: str | None = setting(None, short="-o", help="where")
    dry: bool = setting(False, help="do nothing")
    tag: list[str] = setting(factory=list, repeat=True, help="labels")
    knobs: dict[str, Any] = flatten(Knobs, help=lambda f: f"knob {f.name}")


def _parse(cls: type, argv: list[str]) -> Any:
    p = argparse.ArgumentParser()
    add_options(p, cls)
    return from_namespace(cls, p.parse_args(argv))


def test_options_parse_into_the_settings_and_back() -> None:
    s = _parse(Toy, ["in.mp4", "--count", "7", "-o", "x", "--dry", "--tag", "a", "--tag", "b",
                     "--depth", "5"])  # fmt: skip
    assert s == Toy(source="in.mp4", count=7, output="x", dry=True, tag=["a", "b"],
                    knobs={"depth": 5})  # fmt: skip
    # only the flattened fields given are overrides: the others keep Knobs' defaults
    assert Knobs(**s.knobs) == Knobs(depth=5, gain=0.5)
    # the command line of a settings object gives it back
    assert _parse(Toy, command_line(s)) == s
    assert command_line(Toy(source="a")) == ["a"]  # defaults are not repeated


def test_bounds_and_choices_are_one_line_errors() -> None:
    with pytest.raises(InputError, match=r"^--count must be >= 1, got 0$"):
        check(Toy(source="a", count=0))
    with pytest.raises(SystemExit):
        _parse(Toy, ["a", "--mode", "medium"])
    with pytest.raises(SystemExit):
        _parse(Toy, ["--count", "2"])  # the required argument is missing


def test_pipeline_params_are_converted_and_named_in_errors() -> None:
    s = from_params(Toy, {"source": "a", "count": "12", "tag": "x", "depth": 2}, "w")
    assert (s.count, s.tag, s.knobs, s.workdir) == (12, ["x"], {"depth": 2}, "w")
    with pytest.raises(InputError, match="parameter 'count' must be int, got 'many'"):
        from_params(Toy, {"source": "a", "count": "many"}, "w")
    with pytest.raises(InputError, match="parameter 'dry' must be true or false"):
        from_params(Toy, {"source": "a", "dry": "yes"}, "w")
    with pytest.raises(InputError, match="unknown parameter 'colour'"):
        from_params(Toy, {"source": "a", "colour": 1}, "w")
    with pytest.raises(InputError, match="missing parameter 'source'"):
        from_params(Toy, {}, "w")


def test_adding_a_setting_is_one_line() -> None:
    @dataclass(kw_only=True)
    class Toy2(Toy):
        ratio: float = setting(0.25, help="a new knob")  # the one line

    assert _parse(Toy2, ["a", "--ratio", "0.5"]).ratio == 0.5
    assert from_params(Toy2, {"source": "a", "ratio": 2}, "w").ratio == 2.0
    assert "--ratio" in [o.flag for o in options(Toy2)]


@pytest.mark.parametrize("name", sorted(STAGES))
def test_every_command_is_generated_from_its_settings(name: str) -> None:
    """Every option has help; every setting is reachable from the command line."""
    parser, stage = cli.build_parser(name)
    settings_cls, run = stage.load()
    assert callable(run) and issubclass(settings_cls, Settings)
    for o in options(settings_cls):
        assert o.meta.help, f"{name} {o.flag} has no help"
    assert "usage" in parser.format_help()


def test_train_does_not_offer_what_the_dataset_decides(capsys) -> None:
    for flag in ("--resolution", "--channels", "--train-images"):
        with pytest.raises(SystemExit):
            cli.main(["train", flag, "80"])
    assert cli.main(["train", "--set", "channels=1"]) == 1
    assert "channels is the dataset's" in capsys.readouterr().err


@dataclass(kw_only=True)
class Echo(Settings):
    """A stage that records the settings it was run with."""

    text: str = setting(positional=True, help="what to write")
    times: int = setting(1, minimum=1, help="repeats")


CALLS: list[Echo] = []


def _echo(s: Echo) -> int:
    CALLS.append(s)
    (Path(s.workdir) / "echo.txt").write_text(s.text * s.times)
    return 0


@dataclasses.dataclass(frozen=True)
class _EchoStage(Stage):
    def load(self):  # noqa: ANN201 - no command module: the settings and run are here
        return Echo, _echo


def test_runner_calls_run_with_settings_and_caches(tmp_path: Path, monkeypatch) -> None:
    monkeypatch.setitem(STAGES, "echo", _EchoStage("echo", "-", "write text"))
    monkeypatch.setattr(cli, "main", None)  # the runner must not go through the CLI
    spec = tmp_path / "pipelines.yaml"
    spec.write_text("p:\n  stages:\n    e:\n      command: echo\n"
                    "      params: {text: ab, times: '3'}\n")  # fmt: skip
    CALLS.clear()
    for expect in ("ran", "cached"):
        runner = Runner(build_pipeline(load_specs(spec), "p", spec), tmp_path / "runs")
        assert [r.status for r in runner.run()] == [expect]
    assert CALLS == [Echo(text="ab", times=3, workdir=str(tmp_path / "runs/p/e"))]
    assert (tmp_path / "runs/p/e/echo.txt").read_text() == "ababab"
    spec.write_text("p:\n  stages:\n    e: {command: echo, params: {times: x}}\n")
    with pytest.raises(SpecError, match="pipelines.yaml:3: parameter 'times' .* must be int"):
        build_pipeline(load_specs(spec), "p", spec)
