"""`dronecap ingest FOLDER` on stream defects and sensor formats, and a white-backdrop orbit."""

from __future__ import annotations

import json

import cv2
import numpy as np

from dronecap.capture.selection import REASONS, SelectionParams, select_frames
from dronecap.capture.tables import extra_to_tables
from dronecap.cli import main
from dronecap.datasets import open_dataset
from tests.capture.conftest import pan, texture, white_orbit_frames, write_video
from tests.capture.test_defects import mosaic


def test_torn_upside_down_and_repeated_frames_are_named(tmp_path, capsys):
    folder = tmp_path / "stream"
    folder.mkdir()
    frames = pan(30, (160, 160), 2.0)
    frames[8] = frames[8].copy()
    frames[8][110:] = 0  # bottom third lost
    frames[15] = frames[15][::-1, ::-1].copy()  # delivered upside down
    frames[22] = frames[21]  # the previous buffer again
    for i, f in enumerate(frames):
        cv2.imwrite(str(folder / f"frame_{i}.png"), f)
    assert main(["ingest", str(folder), "--workdir", str(tmp_path)]) == 0
    err = capsys.readouterr().err
    assert "1 torn frames dropped: frame_8.png" in err
    assert "1 upside-down frames dropped: frame_15.png" in err
    assert "1 frozen frames dropped: frame_22.png" in err
    ds = open_dataset(tmp_path / "frames.h5")
    reason = ds.extra["reason"]
    assert REASONS[reason[8]] == "torn" and REASONS[reason[15]] == "upside_down"
    assert REASONS[reason[22]] == "frozen"
    assert ds.attrs["defects"] == {"torn": [8], "upside_down": [15], "frozen": [22]}
    assert ((reason >= 2) & (reason != REASONS.index("redundant"))).sum() == 3
    # The stored tables replay to the same decision, defects included.
    stored = ds.provenance["params"]["selection"]
    again = select_frames(extra_to_tables(ds.extra), SelectionParams(**stored))
    np.testing.assert_array_equal(again.keep, ds.extra["keep"].astype(bool))
    np.testing.assert_array_equal(again.reason, reason)


def test_raw_bayer_frames_are_demosaiced(tmp_path, capsys):
    folder = tmp_path / "raw"
    folder.mkdir()
    rng = np.random.default_rng(0)
    colour = [texture(160, 400, seed=s).astype(np.float32) for s in (1, 2, 3)]
    scene = np.stack([0.5 * colour[0], 0.8 * colour[1], colour[2]], 2).astype(np.uint8)
    for i in range(12):
        view = scene[:, 4 * i : 4 * i + 160]
        noisy = np.clip(view + rng.normal(0, 1, view.shape), 0, 255).astype(np.uint8)
        cv2.imwrite(str(folder / f"{i:05d}.pgm"), mosaic(noisy, "GRBG"))
    assert main(["ingest", str(folder), "--workdir", str(tmp_path)]) == 0
    assert "raw Bayer GRBG mosaic demosaiced" in capsys.readouterr().out
    ds = open_dataset(tmp_path / "frames.h5")
    assert ds.attrs["bayer"] == "GRBG"
    i = int(ds.source_index[0])
    ref = cv2.cvtColor(scene[:, 4 * i : 4 * i + 160], cv2.COLOR_BGR2GRAY)
    assert np.abs(ds.images[0, :, :, 0].astype(float) - ref).mean() < 3.0
    # --bayer none keeps the mosaic as it is (gray with a 2x2 pattern).
    assert main(["ingest", str(folder), "--workdir", str(tmp_path), "--bayer", "none"]) == 0
    assert open_dataset(tmp_path / "frames.h5").attrs["bayer"] is None


def test_white_backdrop_orbit_keeps_close_overlapping_views(tmp_path, lego_dir):
    """60 lego test views (3.3 degrees apart) on pure white, as an mp4: none is over-exposed
    or blurred, kept views stay close (at most 3 frames, 10 degrees, apart) and every kept
    neighbour shares most of its tracks."""
    video = write_video(
        tmp_path / "orbit.mp4", white_orbit_frames(lego_dir, range(60)), fourcc="mp4v"
    )
    assert main(["-q", "ingest", str(video), "--workdir", str(tmp_path)]) == 0
    ds = open_dataset(tmp_path / "frames.h5")
    reason = [REASONS[r] for r in ds.extra["reason"]]
    assert set(reason) <= {"kept", "kept_gap", "redundant"}  # no clipped, blurry, blank
    assert np.mean(ds.extra["clipped"]) > 0.5  # although most pixels are saturated white
    k = np.asarray(ds.source_index)
    assert ds.n >= 30 and np.diff(k).max() <= 3
    doc = json.loads((lego_dir / "transforms_test.json").read_text())
    z = -np.array([f["transform_matrix"] for f in doc["frames"][:60]])[k, :3, 2]
    gap = np.degrees(np.arccos(np.clip((z[1:] * z[:-1]).sum(1), -1, 1)))
    assert gap.max() < 11.0
    surv = ds.extra["pair_survival"][k[1:], np.diff(k) - 1]
    assert surv.min() >= 0.5
