"""matplotlib is the optional ``plots`` extra: without it the commands that draw a figure still
succeed and write their outputs, skip the figure and say so in one line per process."""

from __future__ import annotations

import json
import sys

import cv2
import pytest

from dronecap import plots
from dronecap.camera import Camera
from dronecap.cli import main
from tests.calibration.conftest import board_images, board_poses


@pytest.fixture
def no_matplotlib(monkeypatch):
    """matplotlib unimportable (``import matplotlib`` raises ModuleNotFoundError), and the
    once-per-process notice not yet given."""
    monkeypatch.setitem(sys.modules, "matplotlib", None)
    plots._say_skipped.cache_clear()
    yield
    plots._say_skipped.cache_clear()


def skipped_lines(err: str) -> list[str]:
    return [line for line in err.splitlines() if plots.SKIPPED in line]


def test_cost_search_without_matplotlib_prints_its_choice_and_skips_the_plot(
    tmp_path, capsys, no_matplotlib
):
    png = tmp_path / "p.png"
    assert main(["cost", "--search", "--budget-l3", "32MB", "--plot", str(png)]) == 0
    got = capsys.readouterr()
    assert "chosen: b8k-t13" in got.out and "wrote" not in got.out
    assert skipped_lines(got.err) == [f"dronecap: {plots.SKIPPED}"]
    assert not png.exists()


def test_calibrate_without_matplotlib_writes_the_calibration(tmp_path, capsys, no_matplotlib):
    lens = Camera(300.0, 302.0, 165.0, 118.0, 320, 240, "OPENCV", (-0.25, 0.08, 0.001, -0.001))
    names = []
    for i, im in enumerate(board_images(lens, board_poses(6))):
        names.append(str(tmp_path / f"v{i}.png"))
        cv2.imwrite(names[-1], im)
    out, png = tmp_path / "calib.json", tmp_path / "calib.png"
    board = ["--pattern", "chessboard", "--board", "9x6", "--subpix-window", "0"]
    assert main(["calibrate", *names, *board, "--plot", str(png), "-o", str(out)]) == 0
    assert json.loads(out.read_text())["fx"] == pytest.approx(300.0, rel=0.01)
    assert len(skipped_lines(capsys.readouterr().err)) == 1
    assert not png.exists()


def test_the_notice_is_given_once_however_many_figures_are_skipped(tmp_path, capsys, no_matplotlib):
    metrics = tmp_path / "run" / "metrics.json"
    metrics.parent.mkdir()
    metrics.write_text(json.dumps({"history": [{"step": 1, "loss": 0.1, "psnr": 10.0}]}))
    assert plots.training_curve(metrics, tmp_path / "a.png") is None
    assert plots.training_curve(metrics, tmp_path / "b.png") is None
    assert len(skipped_lines(capsys.readouterr().err)) == 1
    assert not list(tmp_path.glob("*.png"))


def test_with_matplotlib_the_figure_is_drawn(tmp_path, capsys):
    pytest.importorskip("matplotlib")
    metrics = tmp_path / "run" / "metrics.json"
    metrics.parent.mkdir()
    metrics.write_text(json.dumps({"history": [{"step": 1, "loss": 0.1, "psnr": 10.0}]}))
    png = plots.training_curve(metrics, tmp_path / "a.png")
    assert png is not None and cv2.imread(str(png)) is not None
    assert not skipped_lines(capsys.readouterr().err)
