"""`render --mp4` writes a video browsers play: H.264 when OpenCV has it, else animated WebP/GIF."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from dronecap.nerf.outputs import write_video


def test_video_is_h264_or_an_animation_with_every_frame(tmp_path: Path) -> None:
    frames = [np.full((24, 32, 1), i / 7, np.float32) for i in range(8)]
    path = write_video(tmp_path / "video", frames, fps=12)
    assert path.exists() and path.stem == "video"
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]  # no partial left
    if path.suffix == ".mp4":
        cap = cv2.VideoCapture(str(path))
        fourcc = int(cap.get(cv2.CAP_PROP_FOURCC)).to_bytes(4, "little").decode().lower()
        assert fourcc in ("avc1", "h264")
        assert int(cap.get(cv2.CAP_PROP_FRAME_COUNT)) == 8
        return
    from PIL import Image

    with Image.open(path) as im:
        assert path.suffix in (".webp", ".gif") and im.n_frames == 8
        im.seek(7)
        last = np.asarray(im.convert("L"))
    assert abs(int(last.mean()) - 255) <= 1 and last.shape == (24, 32)
