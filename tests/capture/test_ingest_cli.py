"""``dronecap ingest`` end to end on small videos written here, and every bad input."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from dronecap.cli import main
from dronecap.datasets import open_dataset
from tests.capture.conftest import pan, texture, write_video


def ingest(tmp_path: Path, *args: str) -> int:
    return main(["ingest", *args, "--workdir", str(tmp_path)])


def test_ingest_writes_frames_h5_with_tables_and_intrinsics(tmp_path, pan_video, capsys):
    assert ingest(tmp_path, str(pan_video), "--intrinsics", "300,300,160,120") == 0
    out = capsys.readouterr().out
    assert "decoded 48 frames" in out and "frames/s" in out
    ds = open_dataset(tmp_path / "frames.h5", kinds=("frames",))
    assert ds.images.dtype == np.uint8 and ds.images.shape[1:] == (160, 160, 1)
    # 2 px per output frame, min_motion 8 px: the frame 8 px on is past it, so one frame in
    # three (6 px) is kept.
    assert 14 <= ds.n <= 17 and np.median(np.diff(ds.source_index)) == 3
    assert np.all(np.diff(ds.source_index) > 0) and np.diff(ds.source_index).max() <= 15
    np.testing.assert_allclose(ds.timestamps, ds.source_index / 30.0, atol=1e-6)
    # crop 240x240 at x0 = 40, scale 2/3: fx = 200, cx = (160 - 40) * 2/3 = 80, cy = 80
    k = ds.intrinsics
    assert (k.fx, k.cx, k.cy, k.width) == (
        pytest.approx(200),
        pytest.approx(80),
        pytest.approx(80),
        160,
    )
    n = len(ds.extra["reason"])
    assert n == 48 and ds.extra["keep"].sum() == ds.n
    assert list(ds.extra["reason_legend"][:2]) == ["kept", "kept_gap"]
    assert ds.attrs["decoded"] == 48 and ds.provenance["stage"] == "ingest"
    # The stored image is the cropped, area-resized first kept frame.
    cap = cv2.VideoCapture(str(pan_video))
    for _ in range(int(ds.source_index[0]) + 1):
        _, frame = cap.read()
    ref = cv2.resize(
        cv2.cvtColor(frame, cv2.COLOR_BGR2GRAY)[:, 40:280], (160, 160), interpolation=cv2.INTER_AREA
    )
    np.testing.assert_array_equal(ds.images[0, :, :, 0], ref)


def test_replay_changes_thresholds_without_decoding(tmp_path, pan_video, capsys):
    frames = tmp_path / "frames.h5"
    assert ingest(tmp_path, str(pan_video), "--min-motion", "2") == 0
    first = open_dataset(frames)
    pan_video.unlink()  # replay must not need the video
    capsys.readouterr()
    sub = tmp_path / "sub.h5"
    assert ingest(tmp_path, "--replay", str(frames), "--min-motion", "8", "-o", str(sub)) == 0
    assert "replay of" in capsys.readouterr().out
    second = open_dataset(sub)
    assert second.n < first.n / 2
    assert set(second.source_index) <= set(first.source_index)
    np.testing.assert_array_equal(second.extra["keep"].sum(), second.n)
    # Asking for denser frames than were stored says a re-ingest is needed for them.
    assert ingest(tmp_path, "--replay", str(sub), "--min-motion", "1") == 0
    assert "were not stored" in capsys.readouterr().out


def test_image_folder_in_natural_order(tmp_path):
    folder = tmp_path / "imgs"
    folder.mkdir()
    frames = pan(12, (160, 160), 3.0)
    for i, f in enumerate(frames):
        cv2.imwrite(str(folder / f"img{i}.png"), f)  # img10 must come after img9
    assert ingest(tmp_path, str(folder), "--fps", "10", "--min-motion", "0.1") == 0
    ds = open_dataset(tmp_path / "frames.h5")
    assert ds.names[:3] == ["img0.png", "img1.png", "img2.png"]
    order = [int(n[3:-4]) for n in ds.names]
    assert order == sorted(order)
    np.testing.assert_allclose(ds.timestamps, ds.source_index / 10.0)
    np.testing.assert_array_equal(ds.images[0, :, :, 0], frames[int(ds.source_index[0])])


def test_sharp_frames_win_and_hovering_is_thinned_on_a_real_video(tmp_path):
    # 30 frames moving 3 px/frame at 160 px, then 60 hovering (static view + noise), then 30
    # moving; every 5th moving frame is blurred (a gust).
    rng = np.random.default_rng(0)
    tex = texture(160, 600)
    xs = np.r_[np.arange(30) * 3.0, np.full(60, 90.0), 90 + np.arange(1, 31) * 3.0]
    frames = []
    for i, x in enumerate(xs):
        f = cv2.warpAffine(tex, np.float32([[1, 0, -x], [0, 1, 0]]), (160, 160))
        if i % 5 == 2 and not 30 <= i < 90:
            f = cv2.blur(f, (9, 1))
        noise = rng.normal(0, 1.5, f.shape)
        frames.append(np.clip(f + noise, 0, 255).astype(np.uint8))
    video = write_video(tmp_path / "hover.mkv", frames, fourcc="FFV1")
    assert ingest(tmp_path, str(video), "--min-motion", "6", "--max-gap", "20") == 0
    ds = open_dataset(tmp_path / "frames.h5")
    k = ds.source_index
    reasons = ds.extra["reason"]
    blurred = [i for i in range(120) if i % 5 == 2 and not 30 <= i < 90]
    assert not np.isin(blurred, k).any()  # no blurred frame kept
    assert all(reasons[i] in (6, 7) for i in blurred)  # blurry or beaten by a sharp neighbour
    hover = ((k >= 35) & (k < 90)).sum()
    moving = ((k < 30) | (k >= 90)).sum()
    assert hover <= 3 and moving >= 15  # 55 hover frames -> about one per max_gap
    assert np.diff(k).max() <= 20


def test_odd_size_161x97_works(tmp_path, capsys):
    video = write_video(tmp_path / "odd.avi", pan(20, (161, 97), 2.0))
    assert ingest(tmp_path, str(video), "--min-motion", "1") == 0
    captured = capsys.readouterr()
    assert "upsampled" in captured.err
    assert open_dataset(tmp_path / "frames.h5").images.shape[1:] == (160, 160, 1)


def bad(tmp_path: Path, capsys, *args: str) -> str:
    """Run ingest expecting failure: exit 1, one stderr line, no frames.h5."""
    rc = ingest(tmp_path, *args)
    err = capsys.readouterr().err.strip()
    assert rc == 1
    assert len(err.splitlines()) == 1 and "Traceback" not in err, err
    assert not (tmp_path / "frames.h5").exists()
    assert not list(tmp_path.glob(".frames.h5*"))
    return err


def test_missing_file(tmp_path, capsys):
    assert "no such file" in bad(tmp_path, capsys, str(tmp_path / "nope.mp4"))


def test_not_a_video(tmp_path, capsys):
    p = tmp_path / "notes.mp4"
    p.write_text("these are not frames\n" * 50)
    assert "not a video" in bad(tmp_path, capsys, str(p))


def test_zero_decodable_frames(tmp_path, capsys):
    good = write_video(tmp_path / "good.avi", pan(30, (160, 120), 2.0))
    p = tmp_path / "headonly.avi"
    p.write_bytes(good.read_bytes()[:6000])  # container header, no complete frame
    err = bad(tmp_path, capsys, str(p))
    assert "no decodable frames" in err or "truncated" in err


def test_truncated_video_says_how_much(tmp_path, capsys):
    good = write_video(tmp_path / "good.avi", pan(40, (160, 120), 2.0))
    p = tmp_path / "cut.avi"
    p.write_bytes(good.read_bytes()[: good.stat().st_size // 2])
    err = bad(tmp_path, capsys, str(p))
    assert "truncated: decoded" in err and "of 40 frames" in err
    assert ingest(tmp_path, str(p), "--allow-truncated", "--min-motion", "1") == 0
    assert "truncated" in capsys.readouterr().err
    assert (tmp_path / "frames.h5").exists()


def test_truncated_mp4_without_index(tmp_path, capsys):
    good = write_video(tmp_path / "good.mp4", pan(30, (160, 120), 2.0), fourcc="mp4v")
    p = tmp_path / "cut.mp4"
    p.write_bytes(good.read_bytes()[: good.stat().st_size // 2])
    assert "cut off" in bad(tmp_path, capsys, str(p))


def test_one_frame_video(tmp_path, capsys):
    p = write_video(tmp_path / "one.avi", pan(1, (160, 120), 0.0))
    assert "only one decodable frame" in bad(tmp_path, capsys, str(p))


def test_all_black_video(tmp_path, capsys):
    p = write_video(tmp_path / "black.avi", [np.zeros((120, 160), np.uint8)] * 20)
    assert "nothing to reconstruct" in bad(tmp_path, capsys, str(p))


def test_frozen_video(tmp_path, capsys):
    p = write_video(tmp_path / "frozen.mkv", [texture(120, 160)] * 20, fourcc="FFV1")
    err = bad(tmp_path, capsys, str(p))
    assert "nothing to reconstruct" in err and "frozen" in err


def test_empty_folder_and_bad_options(tmp_path, capsys):
    (tmp_path / "empty").mkdir()
    assert "no images" in bad(tmp_path, capsys, str(tmp_path / "empty"))
    good = write_video(tmp_path / "good.avi", pan(10, (160, 120), 2.0))
    assert "crop" in bad(tmp_path, capsys, str(good), "--crop", "0,0,500,500")
