"""Resolve once: the trained model, its run folder and its cost report hold one configuration."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from dronecap.cli import main
from dronecap.errors import InputError
from dronecap.nerf.config import PRESETS, preset
from dronecap.nerf.resolve import Resolved, resolve


def test_resolve_fills_in_what_the_data_decides(cube_rgb):
    r = resolve(preset("test").replace(auto_n_max=True), cube_rgb)
    # cube: AABB side 2, mean near 1.5, focal 24 / (2 tan 0.4) = 28.47 px
    # -> footprint 1.5 / 28.47 = 0.0527 -> ceil(2 / 0.0527) = 38 cells
    focal = 24 / (2 * math.tan(0.4))
    assert r.config.n_max == math.ceil(2 / (1.5 / focal)) == 38
    assert (r.config.channels, r.config.resolution, r.config.train_images) == (3, 24, 9)
    assert set(r.reasons) == {"n_max", "channels", "resolution", "train_images", "mlp_dtype",
                              "learn_exposure", "learn_vignetting", "far_field"}  # fmt: skip
    assert "auto_n_max" in r.reasons["n_max"]
    # a fixed n_max stays, and says so
    assert resolve(preset("test"), cube_rgb).config.n_max == 256
    assert Resolved.from_dict(json.loads(json.dumps(r.to_dict()))).to_dict() == r.to_dict()


@pytest.mark.parametrize(
    ("asked", "precision", "native", "products"),
    [("auto", "fp32", True, "bf16"), ("auto", "fp32", False, "fp32"),
     ("auto", "fp16", True, "fp32"), ("auto", "bf16", True, "bf16"),
     ("fp32", "fp32", True, "fp32"), ("bf16", "fp32", False, "bf16")],
)  # fmt: skip
def test_mlp_dtype_is_decided_once_for_this_cpu(
    cube_rgb, monkeypatch, asked, precision, native, products
):
    from dronecap.nerf import config

    monkeypatch.setattr(config, "fast_bf16", lambda: native)
    r = resolve(preset("test").replace(mlp_dtype=asked, precision=precision), cube_rgb)
    assert r.config.mlp_dtype == products
    assert ("configuration" in r.reasons["mlp_dtype"]) == (asked != "auto")


def test_bf16_products_cannot_emulate_fp16_storage(cube_rgb):
    with pytest.raises(InputError, match="mlp_dtype bf16 cannot emulate fp16"):
        resolve(preset("test").replace(mlp_dtype="bf16", precision="fp16"), cube_rgb)


def test_split_without_train_frames_is_refused(cube_rgb):
    import dataclasses

    only_test = dataclasses.replace(cube_rgb, split=np.full(cube_rgb.n, 2, np.int8))
    with pytest.raises(InputError, match="no train frames"):
        resolve(preset("test"), only_test)


# every preset: train zero steps (the model is built, saved and costed), then compare
@pytest.mark.parametrize("name", sorted(PRESETS))
def test_cost_json_and_cost_command_model_the_trained_n_max(name, cube_h5, tmp_path):
    from dronecap.nerf.trainer import Trainer

    run = tmp_path / "run"
    argv = ["train", str(cube_h5), "--preset", name, "--steps", "0", "--out", str(run)]
    assert main([*argv, "--no-eval", "--no-progress", "--threads", "1"]) == 0
    from_train = json.loads((run / "cost.json").read_text())
    assert main(["cost", str(run), "--json", str(tmp_path / "again.json")]) == 0
    from_command = json.loads((tmp_path / "again.json").read_text())
    assert from_train == from_command
    trained = Trainer.load(run / "checkpoint.pt")
    finest = trained.field.encoding.resolutions[-1]
    assert from_train["config"]["n_max"] == finest == trained.cfg.n_max
    assert from_train["config"]["channels"] == trained.field.color_mlp[-1].out_features == 3
    assert from_train["config"]["resolution"] == 24 and from_train["assumptions"]["n_images"] == 9
    run_info = json.loads((run / "run.json").read_text())
    assert run_info["config"]["n_max"] == finest and "n_max" not in run_info
    if PRESETS[name].auto_n_max:
        assert finest != PRESETS[name].n_max  # sized to the cube, not the preset's 2048


def test_cost_of_a_folder_with_only_a_checkpoint(cube_rgb, tmp_path):
    """A federated run folder holds the global model's checkpoint.pt and no run.json: `dronecap
    cost RUN` costs the configuration stored in the checkpoint."""
    from dronecap.nerf.trainer import Trainer

    run = tmp_path / "federated"
    tr = Trainer(preset("test").replace(auto_n_max=True), cube_rgb)
    tr.save(run / "checkpoint.pt")
    assert main(["cost", str(run)]) == 0
    rep = json.loads((run / "cost.json").read_text())
    assert rep["config"]["n_max"] == tr.field.encoding.resolutions[-1] == 38
