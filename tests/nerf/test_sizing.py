"""Scene sizing: each choice worked out by hand from the bounds, cameras and a memory model."""

from __future__ import annotations

import json
import math

import pytest

from dronecap.nerf.config import preset
from dronecap.nerf.sizing import SceneFacts, Sizing, size_to_scene

# a 2 x 2 x 2 scene seen from 4 units with a 200 px focal length: footprint 0.02
CUBE = SceneFacts((2.0, 2.0, 2.0), near=4.0, focal=200.0, width=100, height=80, channels=1,
                  train_images=30)  # fmt: skip


def table_memory(cfg) -> float:
    """A hand memory model: 1000 bytes per table row, nothing else."""
    return 1000.0 * 2**cfg.log2_hashmap


def values(s: Sizing) -> dict:
    return {c.field: c.value for c in s.choices}


def test_choices_follow_the_footprint():
    s = size_to_scene(preset("tiny-dronerf"), CUBE, table_memory, 1000.0 * 2**14 + 1)
    v = values(s)
    # footprint 4 / 200 = 0.02: 2 / 0.02 = 100 cells on the longest side
    assert v["n_max"] == s.config.n_max == 100
    # diagonal 2 * sqrt(3) = 3.464 / 0.02 = 173.2 -> 174 candidates
    assert v["march_steps"] == s.config.march_steps == 174
    # 100 / 4 = 25 -> nearest power of two 32
    assert v["grid_res"] == s.config.grid_res == 32
    # the budget holds 2^14 rows of 1000 bytes, not 2^15
    assert v["log2_hashmap"] == s.config.log2_hashmap == 14
    assert v["channels"] == s.config.channels == 1
    assert s.config.auto_n_max is False
    assert s.memory_bytes == 1000.0 * 2**14
    # the MLPs and the batch are the preset's
    base = preset("tiny-dronerf")
    assert (s.config.hidden, s.config.batch_samples, s.config.levels) == (
        base.hidden, base.batch_samples, base.levels)  # fmt: skip
    assert len(s.lines()) == 5 and all(": " in line for line in s.lines())


def test_cameras_inside_the_scene_are_capped_at_two_cells_per_pixel():
    # near 0.1 / focal 200: footprint 0.0005 would ask 2 / 0.0005 = 4000 cells and
    # 3.464 / 0.0005 = 6929 steps; the 100 px wide images cap both at 2 * 100 = 200
    close = SceneFacts((2.0, 2.0, 2.0), 0.1, 200.0, 100, 80, 3, 30)
    s = size_to_scene(preset("tiny-dronerf"), close, table_memory, 1e12)
    assert (s.config.n_max, s.config.march_steps) == (200, 200)
    assert "capped at 2 per image pixel (200)" in values_reasons(s)["n_max"]
    assert s.config.grid_res == 64  # 200 / 4 = 50 -> 64


def values_reasons(s: Sizing) -> dict:
    return {c.field: c.reason for c in s.choices}


def test_table_capped_at_what_the_finest_level_needs():
    # surface of the cube in footprints: 6 * 100^2 = 60000 rows -> 2^15.87 -> at most 2^16
    s = size_to_scene(preset("tiny-dronerf"), CUBE, table_memory, 1e12)
    assert s.config.log2_hashmap == 16 == math.ceil(math.log2(6 * 100**2))


def test_user_fields_are_kept():
    s = size_to_scene(
        preset("tiny-dronerf").replace(n_max=512, log2_hashmap=13),
        CUBE, table_memory, 1e12, fixed={"n_max", "log2_hashmap"},
    )  # fmt: skip
    v = {c.field: c for c in s.choices}
    assert s.config.n_max == 512 and v["n_max"].reason == "set by the user"
    assert s.config.log2_hashmap == 13 and v["log2_hashmap"].reason == "set by the user"
    assert s.config.grid_res == 128  # 512 / 4 -> clamped to 128


def test_budget_too_small_is_refused():
    with pytest.raises(ValueError, match="smallest table"):
        size_to_scene(preset("tiny-dronerf"), CUBE, table_memory, 1000.0 * 2**11)


def test_no_budget_keeps_the_preset_table():
    s = size_to_scene(preset("tiny-dronerf"), CUBE)
    assert s.config.log2_hashmap == 13 and s.memory_bytes is None


def test_lego_sized_with_the_gap9_model_fits_21_mb():
    """lego 160 px bounds and cameras with the real GAP9 cost model and the paper's 21 MB."""
    from dronecap.gap9.model import cost_report

    def mem(cfg):
        return cost_report(cfg)["memory"]["untiled"]["total"]

    lego = SceneFacts((1.481, 2.489, 1.733), near=2.484, focal=222.2, width=160, height=160,
                      channels=3, train_images=100)  # fmt: skip
    s = size_to_scene(preset("tiny-dronerf"), lego, mem, 21e6)
    assert s.config.n_max == math.ceil(2.489 / (2.484 / 222.2)) == 223
    assert s.config.grid_res == 64
    assert mem(s.config) <= 21e6 < mem(s.config.replace(log2_hashmap=s.config.log2_hashmap + 1))
    assert s.memory_bytes == mem(s.config)


def test_default_train_is_sized_to_the_cube_and_costed_as_trained(cube_h5, tmp_path, capsys):
    """`dronecap train` with no preset on the 24 px cube (f = 24 / (2 tan 0.4) = 28.38 px,
    near 1.5, AABB [-1, 1]^3): footprint 0.05285, n_max ceil(2 / 0.05285) = 38, marching
    ceil(2 sqrt(3) / 0.05285) = 66 candidates capped at 2 x 24 px = 48, grid 38 / 4 -> 8 ->
    clamped to 32, table: the
    cube's surface 6 * 37.84^2 = 8592 rows -> at most 2^14, which fits 21 MB."""
    from dronecap.cli import main

    run = tmp_path / "run"
    args = ["train", str(cube_h5), "--steps", "4", "--batch-samples", "1024", "--out", str(run)]
    assert main([*args, "--no-progress", "--threads", "1"]) == 0
    out = capsys.readouterr().out
    for line in ("n_max = 38:", "march_steps = 48:", "grid_res = 32:", "log2_hashmap = 14:"):
        assert f"sized: {line}" in out, line
    info = json.loads((run / "run.json").read_text())
    cost = json.loads((run / "cost.json").read_text())
    want = {"n_max": 38, "march_steps": 48, "grid_res": 32, "log2_hashmap": 14}
    assert {k: info["config"][k] for k in want} == want
    assert {k: cost["config"][k] for k in want} == want
    assert "pixel footprint" in info["reasons"]["n_max"]
    assert cost["memory"]["untiled"]["total"] <= 21e6
    assert main(["cost", str(run)]) == 0  # `dronecap cost RUN_DIR` models the same network
    assert "/ 14 / 16 x 2" in capsys.readouterr().out  # log2 T / L x F
    again = json.loads((run / "cost.json").read_text())
    assert {k: again["config"][k] for k in want} == want


def test_user_values_survive_the_default_sizing(cube_h5, tmp_path, capsys):
    from dronecap.cli import main

    run = tmp_path / "run"
    args = ["train", str(cube_h5), "--steps", "2", "--batch-samples", "512", "--n-max", "64"]
    assert main([*args, "--out", str(run), "--no-progress", "--threads", "1"]) == 0
    assert "sized: n_max = 64: set by the user" in capsys.readouterr().out
    assert json.loads((run / "run.json").read_text())["config"]["n_max"] == 64


def test_budget_too_small_is_one_line(cube_h5, tmp_path, capsys):
    from dronecap.cli import main

    args = ["train", str(cube_h5), "--budget-mb", "1", "--out", str(tmp_path / "r")]
    assert main([*args, "--no-progress"]) == 1
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "memory budget of 1.0 MB" in err
