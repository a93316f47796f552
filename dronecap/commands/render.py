"""`dronecap render`: render a trained run's test views or an orbit to PNGs (and an MP4).

dronecap render [RUN_DIR] [--orbit N] [--mp4] [--dataset dataset.h5] [--out DIR]
"""

from __future__ import annotations

from dataclasses import dataclass

from dronecap.settings import ProgressSettings, TorchSettings, input_setting, setting


@dataclass(kw_only=True)
class Settings(TorchSettings, ProgressSettings):
    """Options of ``dronecap render``."""

    run_dir: str | None = input_setting("run dir", "WORKDIR/runs/train")
    orbit: int | None = setting(
        None, minimum=1, metavar="N", help="render N views on a circle instead"
    )
    mp4: bool = setting(
        False,
        help="also write the frames as a video browsers play: H.264 video.mp4 when OpenCV has "
        "the encoder, else animated video.webp (or .gif)",
    )
    fps: int = setting(24, minimum=1, maximum=240, help="video frame rate")
    dataset: str | None = setting(None, help="dataset.h5 (default: the one the run was trained on)")
    out: str | None = setting(None, help="output folder (default: RUN_DIR/render)")


def run(s: Settings) -> int:
    """Render and write the images."""
    from pathlib import Path

    from dronecap import workspace
    from dronecap.cpu import check_threads, use_torch_threads
    from dronecap.errors import InputError
    from dronecap.nerf.evaluate import test_views
    from dronecap.nerf.outputs import orbit_poses, write_png, write_video
    from dronecap.nerf.run_dir import open_run
    from dronecap.progress import progress_bar

    run_dir = workspace.resolve(s.workdir, s.run_dir, workspace.TRAIN_RUN)
    check_threads(s.threads)
    use_torch_threads(s.threads)
    trainer, ds = open_run(run_dir, s.dataset)
    out = Path(s.out) if s.out else run_dir / "render"
    if s.orbit is not None:
        poses = orbit_poses(ds.poses, trainer.scene.aabb.mean(0), s.orbit)
        names = [f"orbit_{i:03d}" for i in range(s.orbit)]
        cams = [ds.camera_of(0)] * s.orbit
    else:
        idx = test_views(ds)
        if idx.size == 0:
            where = s.dataset or "the run's dataset"
            raise InputError("dataset has no test or val views; use --orbit N", where)
        poses = ds.poses[idx]
        names = [f"test_{i:03d}" for i in idx]
        cams = [ds.camera_of(int(i)) for i in idx]
    frames = []
    views = list(zip(poses, names, cams, strict=True))
    for pose, name, cam in progress_bar(views, desc="render", unit="view", disable=s.no_progress):
        img = trainer.render(pose, cam)
        write_png(out / f"{name}.png", img)
        frames.append(img)
    video = write_video(out / "video", frames, s.fps) if s.mp4 else None
    print(f"{out}: {len(frames)} views" + (f" + {video.name}" if video else ""))
    return 0
