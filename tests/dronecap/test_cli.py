"""The CLI's global behaviour: optional parts, defaults in help, global flags."""

from __future__ import annotations

import sys

import pytest

from dronecap import cli


def test_missing_optional_part_names_the_extra(monkeypatch, tmp_path, capsys):
    monkeypatch.setitem(sys.modules, "open3d", None)  # `import open3d` now fails as if absent
    for name in [m for m in sys.modules if m.startswith("dronecap.simulator")]:
        monkeypatch.delitem(sys.modules, name)
    code = cli.main(["simulate", "--frames", "20", "--workdir", str(tmp_path)])
    err = capsys.readouterr().err
    assert code == 1
    assert err.strip().splitlines() == [
        "dronecap simulate: error: needs open3d, an optional part of dronecap: "
        "pip install 'dronecap[sim]'"
    ]
    assert not list(tmp_path.iterdir())  # nothing written


def test_help_shows_defaults(capsys):
    parser, _ = cli.build_parser("shard")
    text = parser.format_help()
    assert "(default: 4)" in text or "default 4" in text


def test_quiet_flag_turns_progress_off(monkeypatch, capsys):
    from dronecap import progress

    monkeypatch.setenv(progress.ENV, "bar")  # restored after the test
    assert cli.main(["-q", "run", "--file", "/nonexistent/pipelines.yaml"]) == 1
    assert progress.mode() == "off"


def test_bad_option_value_is_one_line(capsys):
    with pytest.raises(SystemExit) as exc:
        cli.main(["train", "--threads", "abc"])
    err = capsys.readouterr().err
    assert exc.value.code == 2
    assert len(err.strip().splitlines()) == 1 and "--threads" in err and "usage" not in err
