"""`dronecap train / eval / render` end to end on the tiny cube, plus a short real lego run."""

import json

import numpy as np
import pytest

from dronecap.cli import main


def _train(args):
    return main(["train", *args, "--no-progress", "--threads", "1"])


def test_train_resume_eval_render(cube_h5, tmp_path, capsys):
    run = tmp_path / "run"
    assert _train([str(cube_h5), "--preset", "test", "--steps", "20", "--out", str(run)]) == 0
    m = json.loads((run / "metrics.json").read_text())
    assert m["steps"] == 20 and m["test"]["views"] == 3 and len(m["test"]["per_view"]) == 3
    assert np.isfinite(m["test"]["psnr"]) and m["parameters"] > 0
    for name in ("checkpoint.pt", "compare.png", "renders/test_000.png", "run.json", "cost.json"):
        assert (run / name).exists(), name
    # resume: 10 more steps from the checkpoint
    assert _train([str(cube_h5), "--preset", "test", "--steps", "30", "--out", str(run)]) == 0
    assert json.loads((run / "metrics.json").read_text())["steps"] == 30
    # a different configuration in the same run dir is refused with one line
    assert _train([str(cube_h5), "--preset", "test", "--hidden", "16", "--out", str(run)]) == 1
    assert "different configuration (hidden)" in capsys.readouterr().err
    assert main(["eval", str(run), "--no-progress"]) == 0
    out = capsys.readouterr().out
    assert "test PSNR" in out and "(exposure-matched " in out
    assert main(["render", str(run), "--orbit", "3", "--mp4", "--no-progress"]) == 0
    names = sorted(p.name for p in (run / "render").iterdir())
    assert names[:3] == ["orbit_000.png", "orbit_001.png", "orbit_002.png"] and len(names) == 4
    # H.264 where OpenCV's FFmpeg can encode it, else animated WebP (or GIF): see write_video
    assert names[3] in ("video.mp4", "video.webp", "video.gif")
    assert (run / "render" / names[3]).stat().st_size > 0


def test_config_overrides_and_errors(cube_h5, tmp_path, capsys):
    run = tmp_path / "bad"
    assert _train([str(cube_h5), "--set", "nonsense=1", "--out", str(run)]) == 1
    assert "unknown setting 'nonsense'" in capsys.readouterr().err
    assert _train([str(cube_h5), "--auto-n-max", "maybe", "--out", str(run)]) == 1
    assert _train([str(tmp_path / "missing.h5"), "--out", str(run)]) == 1
    assert "no such file" in capsys.readouterr().err


def test_gray_dataset_trains_one_channel_head(cube_gray_h5, tmp_path):
    run = tmp_path / "gray"
    assert (
        _train(
            [
                str(cube_gray_h5),
                "--preset",
                "test",
                "--steps",
                "20",
                "--set",
                "auto_n_max=true",
                "--out",
                str(run),
            ]
        )
        == 0
    )
    m = json.loads((run / "metrics.json").read_text())
    assert m["config"]["channels"] == 1 and m["config"]["auto_n_max"] is True


@pytest.mark.data
def test_short_real_lego_run(lego_dir, tmp_path):
    from dronecap.datasets.blender import import_blender
    from dronecap.datasets.format import open_dataset
    from dronecap.nerf.config import preset
    from dronecap.nerf.trainer import Trainer

    ds = open_dataset(import_blender(lego_dir, tmp_path / "lego.h5", resolution=40, progress=False))
    cfg = preset("test").replace(steps=150, batch_samples=4096, grid_res=32, lr_schedule="constant")
    tr = Trainer(cfg, ds)
    before = tr.evaluate(ds, views=[200, 300])["psnr"]
    tr.train(150)
    after = tr.evaluate(ds, views=[200, 300])["psnr"]
    assert after > before + 3 and after > 15  # learns the scene (test views), not just a blur
