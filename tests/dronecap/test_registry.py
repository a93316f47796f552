"""One face per stage: the registry (dronecap/registry.py) declares a stage's outputs, key figure
and pictures once, and report.html's pictures come from it (no per-command branches)."""

from __future__ import annotations

import dataclasses
from pathlib import Path

from dronecap import registry, report_html
from dronecap.cli import main
from tests.nerf.conftest import cube_h5  # noqa: F401  (pytest fixture)


def test_picture_names_are_unique_within_a_stage():
    for entry in registry.STAGES.values():
        names = [name for name, _ in entry.pictures]
        assert len(names) == len(set(names)), entry.name


def test_a_training_run_gets_the_pictures_its_entry_declares(cube_h5, tmp_path):  # noqa: F811
    run = tmp_path / "train"
    args = ["train", str(cube_h5), "--preset", "test", "--steps", "20", "--out", str(run)]
    assert main([*args, "--no-progress", "--threads", "1"]) == 0
    made = report_html.stage_pictures("train", run, {"dataset": str(cube_h5)}, tmp_path / "pics")
    declared = [f"train_{name}" for name, _ in registry.STAGES["train"].pictures]
    assert [p.name for p in made] == declared and all(p.stat().st_size > 0 for p in made)
    figure = registry.STAGES["train"].figure(run)
    assert "PSNR" in figure and "GAP9" in figure  # the key figure reads metrics.json, cost.json


def test_a_new_stage_is_one_registry_entry(tmp_path, monkeypatch):
    """A stage added to the registry (here a swarm stage drawing one picture) is shown by
    report.html with no other change: stage_pictures reads the entry."""

    def drones(stage_dir: Path, params: dict, out: Path) -> Path:
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_bytes(b"png")
        return out

    swarm = dataclasses.replace(
        registry.STAGES["ingest"], name="swarm", pictures=(("drones.png", drones),)
    )
    monkeypatch.setitem(registry.STAGES, "swarm", swarm)
    made = report_html.stage_pictures("swarm", tmp_path / "swarm", {}, tmp_path / "pics")
    assert [p.name for p in made] == ["swarm_drones.png"]
    assert report_html.stage_pictures("calibrate", tmp_path, {}, tmp_path / "pics") == []
