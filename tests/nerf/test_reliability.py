"""train / eval / render with bad options and wrong data: one line, exit 1, nothing written,
never a number that was not measured (issue 19, classes 3-5)."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest
import torch

from dronecap.cli import main
from dronecap.datasets.format import write_dataset

FAST = ["--preset", "test", "--no-progress", "--threads", "1"]


def _one_line_error(capsys, command: str) -> str:
    err = capsys.readouterr().err
    assert err.startswith(f"dronecap {command}: error:"), err
    assert err.count("\n") == 1, err
    return err


@pytest.mark.parametrize(
    ("option", "value", "says"),
    [
        ("--steps", "abc", "steps takes an integer"),
        ("--steps", "-1", "steps must be >= 0"),
        ("--steps", "1.5", "steps takes an integer"),
        ("--batch-samples", "0", "batch_samples must be >= 1"),
        ("--batch-samples", "-4096", "batch_samples must be >= 1"),
        ("--tile-samples", "0", "tile_samples must be >= 1"),
        ("--march-steps", "0", "march_steps must be >= 1"),
        ("--max-samples-per-ray", "0", "max_samples_per_ray must be >= 1"),
        ("--levels", "0", "levels must be in 1..64"),
        ("--log2-hashmap", "40", "log2_hashmap must be in 1..26"),
        ("--n-max", "8", "n_max must be >= n_min"),
        ("--hidden", "0", "hidden must be >= 1"),
        ("--geo-features", "0", "geo_features must be >= 1"),
        ("--sh-degree", "5", "sh_degree must be in 1..4"),
        ("--lr", "nan", "lr must be a finite number"),
        ("--lr", "-0.01", "lr must be > 0"),
        ("--lr", "inf", "lr must be a finite number"),
        ("--eps", "0", "eps must be > 0"),
        ("--betas", "0.9,1.5", "betas must be two numbers in [0, 1)"),
        ("--grid-decay", "1.5", "grid_decay must be in (0, 1]"),
        ("--grid-every", "0", "grid_every must be >= 1"),
        ("--grid-res", "0", "grid_res must be in 1..1024"),
        ("--precision", "fp8", "precision must be one of fp32, fp16, bf16"),
        ("--mlp-dtype", "fp16", "mlp_dtype must be one of auto, fp32, bf16"),
        ("--lr-schedule", "cosine", "lr_schedule must be one of exp, constant"),
        ("--seed", "-1", "seed must be >= 0"),
        ("--threads", "0", "--threads takes a positive number"),
        ("--checkpoint-every", "0", "--checkpoint-every must be >= 1, got 0"),
    ],
)
def test_bad_train_options_are_one_line_before_any_work(
    option, value, says, cube_h5, tmp_path, capsys
):
    run = tmp_path / "run"
    argv = ["train", str(cube_h5), "--out", str(run), "--preset", "test", "--no-progress"]
    assert main([*argv, option, value]) == 1
    assert says in _one_line_error(capsys, "train")
    assert not run.exists()  # refused before the run folder was made


def test_a_step_count_that_is_not_an_integer_is_refused_by_the_parser(cube_h5, tmp_path, capsys):
    """checkpoint_every is typed (int): the CLI refuses text in one line, exit code 2."""
    run = tmp_path / "run"
    with pytest.raises(SystemExit) as stop:
        main(["train", str(cube_h5), "--out", str(run), "--checkpoint-every", "x"])
    assert stop.value.code == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "--checkpoint-every" in err and "'x'" in err
    assert not run.exists()


def _variant(cube_rgb, tmp_path, name: str, split) -> str:
    path = tmp_path / f"{name}.h5"
    return str(write_dataset(path, dataclasses.replace(cube_rgb, split=split)))


def test_no_train_frames_is_an_error_not_training_on_test_views(cube_rgb, tmp_path, capsys):
    only_test = _variant(cube_rgb, tmp_path, "only_test", np.full(cube_rgb.n, 2, np.int8))
    assert main(["train", only_test, "--out", str(tmp_path / "run"), *FAST]) == 1
    assert "no train frames" in _one_line_error(capsys, "train")
    assert not (tmp_path / "run").exists()


def test_no_test_views_needs_no_eval(cube_rgb, tmp_path, capsys):
    all_train = _variant(cube_rgb, tmp_path, "all_train", np.zeros(cube_rgb.n, np.int8))
    run = tmp_path / "run"
    assert main(["train", all_train, "--out", str(run), "--steps", "5", *FAST]) == 1
    assert "no_eval" in _one_line_error(capsys, "train")  # the setting (--no-eval on the CLI)
    assert not run.exists()
    assert main(["train", all_train, "--out", str(run), "--steps", "5", "--no-eval", *FAST]) == 0
    assert "not evaluated" in capsys.readouterr().out
    m = json.loads((run / "metrics.json").read_text())
    assert m["test"] is None and m["steps"] == 5  # no score that was not measured
    # and eval refuses to invent one
    assert main(["eval", str(run), "--no-progress", "--threads", "1"]) == 1
    assert "no test or val views" in _one_line_error(capsys, "eval")


@pytest.fixture
def trained(cube_h5, tmp_path):
    """A 10-step run of the test preset on the cube."""
    run = tmp_path / "run"
    assert main(["train", str(cube_h5), "--out", str(run), "--steps", "10", *FAST]) == 0
    return run


def test_eval_writes_its_own_file_per_dataset(trained, cube_rgb, tmp_path, capsys):
    before = (trained / "metrics.json").read_bytes()
    assert main(["eval", str(trained), "--no-progress", "--threads", "1"]) == 0
    own = json.loads((trained / "eval_dataset.json").read_text())
    assert own["test"]["views"] == 3 and np.isfinite(own["test"]["psnr"])
    assert own["dataset_sha256"] == own["trained_on_sha256"]
    # another dataset: its own file, the training record untouched
    other = dataclasses.replace(cube_rgb, images=255 - cube_rgb.images)
    other_path = write_dataset(tmp_path / "inverted.h5", other)
    assert main(["eval", str(trained), "--dataset", str(other_path), "--no-progress"]) == 0
    inv = json.loads((trained / "eval_inverted.json").read_text())
    assert inv["dataset"] == str(other_path.resolve())
    assert inv["dataset_sha256"] != inv["trained_on_sha256"]
    assert inv["test"]["psnr"] != own["test"]["psnr"]  # scored on the other images
    assert (trained / "metrics.json").read_bytes() == before


def test_eval_and_render_refuse_non_finite_weights(trained, capsys):
    ck = torch.load(trained / "checkpoint.pt", weights_only=False)
    ck["field"]["encoding.table"][0, 0] = float("nan")
    torch.save(ck, trained / "checkpoint.pt")
    for command in ("eval", "render"):
        assert main([command, str(trained), "--no-progress"]) == 1
        assert "non-finite weights" in _one_line_error(capsys, command)
    assert not list(trained.glob("eval_*.json")) and not (trained / "render").exists()


def test_resume_with_another_dataset_is_refused_unless_asked(trained, cube_rgb, tmp_path, capsys):
    other = dataclasses.replace(cube_rgb, images=255 - cube_rgb.images)
    other_path = str(write_dataset(tmp_path / "other.h5", other))
    ckpt_before = (trained / "checkpoint.pt").read_bytes()
    argv = ["train", other_path, "--steps", "15", *FAST]
    assert main([*argv, "--out", str(trained)]) == 1
    assert "another dataset" in _one_line_error(capsys, "train")
    assert (trained / "checkpoint.pt").read_bytes() == ckpt_before
    # asked for: continues that model on the new data, with a warning, into a new folder
    new = tmp_path / "continued"
    assert main([*argv, "--out", str(new), "--resume-from", str(trained)]) == 0
    assert "warning: continuing the model" in capsys.readouterr().err
    m = json.loads((new / "metrics.json").read_text())
    assert m["steps"] == 15  # 10 steps came from the other run
    info = json.loads((new / "run.json").read_text())
    assert info["resumed_from"] == str(trained.resolve())


def test_out_that_is_a_file_is_one_line(cube_h5, tmp_path, capsys):
    target = tmp_path / "a_file"
    target.write_text("not a folder")
    assert main(["train", str(cube_h5), "--out", str(target), "--steps", "2", *FAST]) == 1
    assert "expected a run folder" in _one_line_error(capsys, "train")
    assert target.read_text() == "not a folder"


def test_run_folder_from_before_resolved_configs_still_loads(cube_h5, tmp_path, capsys):
    """A checkpoint and run.json as the trainer wrote them before this change (the config as
    given, n_max 2048 with auto_n_max, the scene beside it, the auto value in run.json): eval,
    render and cost still read it, and model the n_max that was trained."""
    run = tmp_path / "old"
    argv = ["train", str(cube_h5), "--out", str(run), "--steps", "5", "--auto-n-max", "true"]
    assert main([*argv, *FAST]) == 0
    ck = torch.load(run / "checkpoint.pt", weights_only=False)
    res = ck.pop("resolved")
    trained_n_max = res["config"]["n_max"]
    cfg = res["config"] | {"n_max": 2048, "resolution": 160, "train_images": 100}
    scene = res["scene"] | {"aabb": np.asarray(res["scene"]["aabb"])}
    torch.save(ck | {"config": cfg, "scene": scene}, run / "checkpoint.pt")
    dataset = json.loads((run / "run.json").read_text())["dataset"]
    old_info = {"dataset": dataset, "config": cfg, "n_max": trained_n_max}
    (run / "run.json").write_text(json.dumps(old_info))
    (run / "cost.json").unlink()
    assert main(["eval", str(run), "--no-progress", "--threads", "1"]) == 0
    assert main(["render", str(run), "--orbit", "1", "--no-progress"]) == 0
    assert main(["cost", str(run)]) == 0
    rep = json.loads((run / "cost.json").read_text())
    assert rep["config"]["n_max"] == trained_n_max != 2048
    assert rep["config"]["resolution"] == 24  # re-resolved against the dataset it names
