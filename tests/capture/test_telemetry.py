"""Telemetry CSVs of drone capture folders: layouts, matching, dropped frames, priors, bad input."""

from __future__ import annotations

import csv
from pathlib import Path

import cv2
import numpy as np
import pytest

from dronecap.capture.telemetry import (
    LAYOUTS,
    camera_poses,
    find_capture,
    layout_for,
    match,
    parse_columns,
    unwrap_frame_ids,
)
from dronecap.cli import main
from dronecap.datasets import open_dataset
from tests.capture.conftest import pan

NANO = ["filename", "frame_id", "frame_timestamp", "state_timestamp"]
NANO += ["x", "y", "z", "vx", "vy", "vz", "qx", "qy", "qz", "qw"]
PERIOD_US = 33_333  # 30 Hz
YAW90 = (0.0, 0.0, np.sin(np.pi / 4), np.cos(np.pi / 4))  # body x -> world y (xyzw)


def write_csv(path: Path, header: list[str], rows: list[list[object]]) -> Path:
    with open(path, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(header)
        w.writerows(rows)
    return path


def nanocockpit(folder: Path, delivered: list[int], n_images: int | None = None) -> Path:
    """A NanoCockpit capture: camera frames ``delivered`` (frame_id = frame % 256), the drone
    flying along world x at 3 mm per frame, 1 m up, heading +y (yaw 90 degrees)."""
    (folder / "camera_raw").mkdir(parents=True)
    images = pan(len(delivered), (160, 160), 2.0)
    rows = []
    for k, s in enumerate(delivered[: n_images or len(delivered)]):
        name = f"camera_raw/{k:05d}.png"
        cv2.imwrite(str(folder / name), images[k])
        t = 2_000_000 + s * PERIOD_US
        rows.append([name, s % 256, t, t - 100, 3.0 * s, 0.0, 1000.0, 90, 0, 0, *YAW90])
    return write_csv(folder / "metadata.csv", NANO, rows)


def test_wrapping_frame_id_with_a_known_gap(tmp_path):
    # 300 camera frames; 250..259 lost across the 255 -> 0 wrap, and 3 more at 100..102.
    lost = [*range(100, 103), *range(250, 260)]
    delivered = [s for s in range(300) if s not in lost]
    csv_path = nanocockpit(tmp_path / "cap", delivered)
    frames_dir, found, layout = find_capture(tmp_path / "cap")
    assert found == csv_path and layout.name == "nanocockpit"
    names = sorted(p.name for p in frames_dir.iterdir())
    t = match(csv_path, layout_for(csv_path, {}, layout), names)
    assert t.dropped == lost
    np.testing.assert_array_equal(t.camera_frame, delivered)
    before = t.dropped_before
    assert before[delivered.index(103)] == 3 and before[delivered.index(260)] == 10
    assert before.sum() == len(lost)
    assert t.prior_valid.all()
    np.testing.assert_allclose(t.frame_time, (np.array(delivered) - 0) * PERIOD_US * 1e-6)


def test_frame_id_jumps_of_more_than_256_are_resolved_by_time():
    # 300 frames lost between frames 99 and 400: the id only moves by 301 mod 256 = 45.
    frames = np.r_[np.arange(100), np.arange(400, 450)]
    ids = frames % 256
    got = unwrap_frame_ids(ids, frames * PERIOD_US + 17)
    np.testing.assert_array_equal(got, frames)
    # Without times the jump is taken as the short one (all that 8 bits can say).
    assert unwrap_frame_ids(ids, None)[100] == 99 + 45


def test_priors_follow_the_contract_axes(tmp_path):
    # Body heading +y (yaw 90 degrees): the camera looks along world +y, its x axis (right)
    # is world +x, its y axis (down) is world -z; millimetres become metres.
    csv_path = nanocockpit(tmp_path / "cap", list(range(10)))
    frames_dir, _, layout = find_capture(tmp_path / "cap")
    t = match(csv_path, layout, sorted(p.name for p in frames_dir.iterdir()))
    expected = np.array([[1, 0, 0], [0, 0, 1], [0, -1, 0]], float)  # columns: cam x, y, z
    np.testing.assert_allclose(t.prior_c2w[4, :3, :3], expected, atol=1e-12)
    np.testing.assert_allclose(t.prior_c2w[4, :3, 3], [0.012, 0.0, 1.0])
    # A camera 5 cm ahead of the body origin sits 5 cm further along world +y.
    moved = camera_poses(np.zeros((1, 3)), np.array([YAW90]), np.array([0.05, 0, 0]))
    np.testing.assert_allclose(moved[0, :3, 3], [0.0, 0.05, 0.0], atol=1e-12)


def test_pulp_dronet_frames_match_the_nearest_state_row(tmp_path, capsys):
    folder = tmp_path / "pulp"
    (folder / "images").mkdir(parents=True)
    ticks = [1_000_000 + k * PERIOD_US for k in range(8)] + [2_000_000]  # last: no state near
    for k, t in enumerate(ticks):
        cv2.imwrite(str(folder / "images" / f"{t}.jpeg"), pan(9, (160, 160), 2.0)[k])
    header = ["timeTicks"] + [f"stateEstimate.{a}" for a in ("x", "y", "z", "qx", "qy", "qz", "qw")]
    state_t = np.arange(990_000, 1_300_000, 10_000)  # 100 Hz, ends before the last frame
    rows = [[int(t), t * 1e-6, 0.0, 1.0, 0, 0, 0, 1] for t in state_t]
    write_csv(folder / "state.csv", header, rows)
    frames_dir, csv_path, layout = find_capture(folder)
    assert layout.name == "pulp-dronet" and frames_dir == folder / "images"
    names = sorted((p.name for p in frames_dir.iterdir()), key=lambda n: int(n.split(".")[0]))
    t = match(csv_path, layout, names)
    assert t.prior_valid.tolist() == [True] * 8 + [False]
    nearest = state_t[np.abs(state_t[None, :] - np.array(ticks[:8])[:, None]).argmin(1)]
    np.testing.assert_allclose(t.prior_c2w[:8, 0, 3], nearest * 1e-6)
    assert main(["ingest", str(folder), "--workdir", str(tmp_path)]) == 0
    assert "1 of 9 frames have no telemetry pose" in capsys.readouterr().err
    # The 1 s gap before the last frame is 29 lost frames at the median 33.3 ms period.
    assert len(t.dropped) == round((2_000_000 - ticks[7]) / PERIOD_US) - 1


def test_bitcraze_and_custom_columns(tmp_path):
    folder = tmp_path / "bc"
    folder.mkdir()
    for k, f in enumerate(pan(5, (160, 160), 2.0)):
        cv2.imwrite(str(folder / f"img_{k}.png"), f)
    rows = [[f"img_{k}.png", 100 + 33 * k, 0.5 * k, 0, 1, 1, 0, 0, 0] for k in range(5)]
    path = write_csv(
        folder / "log.csv", ["image_name", "timestamp", "x", "y", "z", "qw", "qx", "qy", "qz"], rows
    )
    _, found, layout = find_capture(folder)
    assert found == path and layout.name == "bitcraze" and layout.time_unit == "ms"
    t = match(path, layout, [f"img_{k}.png" for k in range(5)])
    np.testing.assert_allclose(t.prior_c2w[:, 0, 3], 0.5 * np.arange(5))
    # The same file read through --columns, positions declared in millimetres.
    cols = parse_columns("file=image_name,time=timestamp,unit=mm,time_unit=ms")
    t = match(path, layout_for(path, cols, None), [f"img_{k}.png" for k in range(5)])
    np.testing.assert_allclose(t.prior_c2w[:, 0, 3], 0.5e-3 * np.arange(5))
    with pytest.raises(ValueError, match="--columns"):
        parse_columns("height=z")
    assert {lay.name for lay in LAYOUTS} == {"nanocockpit", "pulp-dronet", "bitcraze"}


def test_ingest_stores_priors_and_dropped_frames(tmp_path, capsys):
    lost = [7, 8, 9]
    delivered = [s for s in range(40) if s not in lost]
    nanocockpit(tmp_path / "cap", delivered)
    assert main(["ingest", str(tmp_path / "cap"), "--workdir", str(tmp_path)]) == 0
    captured = capsys.readouterr()
    assert "3 frames lost in transmission" in captured.out
    assert "3 camera frames lost in transmission: 7, 8, 9" in captured.err
    ds = open_dataset(tmp_path / "frames.h5")
    e = ds.extra
    assert ds.attrs["telemetry"]["format"] == "nanocockpit"
    assert ds.attrs["telemetry"]["dropped_frames"] == lost
    assert e["prior_c2w"].shape == (ds.n, 4, 4) and e["prior_valid"].all()
    camera = np.array(delivered)[ds.source_index]
    np.testing.assert_array_equal(e["frame_id"], camera % 256)
    np.testing.assert_allclose(e["prior_c2w"][:, 0, 3], 3e-3 * camera)
    np.testing.assert_allclose(ds.timestamps, camera * PERIOD_US * 1e-6)
    assert e["dropped_before"][delivered.index(10)] == 3
    # A replay keeps the priors of the frames it keeps.
    sub = tmp_path / "sub.h5"
    args = ["--replay", str(tmp_path / "frames.h5"), "--min-motion", "12", "-o", str(sub)]
    assert main(["ingest", *args, "--workdir", str(tmp_path)]) == 0
    re = open_dataset(sub)
    assert 0 < re.n < ds.n and re.extra["prior_c2w"].shape == (re.n, 4, 4)
    camera = np.array(delivered)[re.source_index]
    np.testing.assert_allclose(re.extra["prior_c2w"][:, 0, 3], 3e-3 * camera)


def bad(tmp_path: Path, capsys, *args: str) -> str:
    rc = main(["ingest", *args, "--workdir", str(tmp_path)])
    err = capsys.readouterr().err.strip()
    assert rc == 1
    assert len(err.splitlines()) == 1 and "Traceback" not in err, err
    assert not (tmp_path / "frames.h5").exists()
    return err


def test_bad_telemetry_names_the_file_and_line(tmp_path, capsys):
    csv_path = nanocockpit(tmp_path / "cap", list(range(12)))
    lines = csv_path.read_text().splitlines()
    header, rows = lines[0], lines[1:]
    # A missing column.
    csv_path.write_text(
        "\n".join([header.replace(",qw", "")] + [r.rsplit(",", 1)[0] for r in rows])
    )
    err = bad(tmp_path, capsys, str(tmp_path / "cap"))
    assert "metadata.csv" in err and "lacks column(s) qw" in err
    # Timestamps going backwards at the 6th row (line 7 of the file).
    swapped = rows.copy()
    swapped[4], swapped[5] = rows[5], rows[4]
    csv_path.write_text("\n".join([header, *swapped]))
    err = bad(tmp_path, capsys, str(tmp_path / "cap"))
    assert "metadata.csv" in err and "line 7" in err and "backwards" in err
    # A value that is not a number, and a zero quaternion.
    broken = rows.copy()
    broken[2] = broken[2].replace(",1000.0,", ",high,")
    csv_path.write_text("\n".join([header, *broken]))
    assert "line 4" in bad(tmp_path, capsys, str(tmp_path / "cap"))
    broken = rows.copy()
    broken[3] = ",".join(broken[3].split(",")[:-4] + ["0", "0", "0", "0"])
    csv_path.write_text("\n".join([header, *broken]))
    assert "line 5: quaternion" in bad(tmp_path, capsys, str(tmp_path / "cap"))
    csv_path.write_bytes(header.encode() + b"\n\xff\xfe binary \x00\n")
    assert "not a readable CSV" in bad(tmp_path, capsys, str(tmp_path / "cap"))


def test_bad_frames_and_options(tmp_path, capsys):
    nanocockpit(tmp_path / "cap", list(range(12)))
    (tmp_path / "cap" / "camera_raw" / "00004.png").write_bytes(b"not a png")
    err = bad(tmp_path, capsys, str(tmp_path / "cap"))
    assert "00004.png" in err and "does not decode" in err
    assert (
        main(["ingest", str(tmp_path / "cap"), "--workdir", str(tmp_path), "--skip-unreadable"])
        == 0
    )
    assert "1 unreadable frames dropped: 00004.png" in capsys.readouterr().err
    (tmp_path / "frames.h5").unlink()
    cv2.imwrite(str(tmp_path / "cap" / "camera_raw" / "00004.png"), np.zeros((80, 80), np.uint8))
    assert "00004.png" in bad(tmp_path, capsys, str(tmp_path / "cap"))  # mixed sizes
    for flag, value in (
        ("--fps", "-5"),
        ("--max-gap", "0"),
        ("--target", "-3"),
        ("--min-overlap", "2"),
    ):
        assert flag in bad(tmp_path, capsys, str(tmp_path / "cap"), flag, value)
    assert "--telemetry" not in bad(
        tmp_path, capsys, str(tmp_path / "cap"), "--telemetry", str(tmp_path / "none.csv")
    )
