"""TUM trajectory files: hand-worked quaternions, round trip, comments, refusals."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from dronecap.datasets.trajectory import read_tum, write_tum
from dronecap.errors import InputError


def test_reads_a_hand_written_file(tmp_path: Path) -> None:
    s = np.sqrt(0.5)
    path = tmp_path / "gt.txt"
    path.write_text(
        "# timestamp tx ty tz qx qy qz qw\n"
        "\n"
        "1.5 1 2 3 0 0 0 1\n"
        f"2.0 -1 0 0.5 0 0 {s} {s}\n"  # 90 degrees about z
        f"2.5,0,0,0,{s},0,0,{s}\n"  # commas too; 90 degrees about x
    )
    t, c2w = read_tum(path)
    np.testing.assert_array_equal(t, [1.5, 2.0, 2.5])
    np.testing.assert_allclose(c2w[0], [[1, 0, 0, 1], [0, 1, 0, 2], [0, 0, 1, 3], [0, 0, 0, 1]])
    np.testing.assert_allclose(c2w[1, :3, :3], [[0, -1, 0], [1, 0, 0], [0, 0, 1]], atol=1e-15)
    np.testing.assert_allclose(c2w[1, :3, 3], [-1, 0, 0.5])
    np.testing.assert_allclose(c2w[2, :3, :3], [[1, 0, 0], [0, 0, -1], [0, 1, 0]], atol=1e-15)


def test_round_trip(tmp_path: Path) -> None:
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(0)
    c2w = np.tile(np.eye(4), (20, 1, 1))
    c2w[:, :3, :3] = Rotation.random(20, random_state=1).as_matrix()
    c2w[:, :3, 3] = rng.normal(size=(20, 3)) * 10
    t = np.sort(rng.uniform(0, 100, 20))
    back_t, back = read_tum(write_tum(tmp_path / "x.txt", t, c2w))
    np.testing.assert_allclose(back_t, t, atol=1e-9)
    np.testing.assert_allclose(back, c2w, atol=1e-8)


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("1 2 3 4 0 0 0\n", "line 1: expected 8 finite numbers"),
        ("# only\n1 2 3 nan 0 0 0 1\n", "line 2: expected 8 finite numbers"),
        ("1 2 3 4 0 0 0 2\n", "line 1: quaternion length 2"),
        ("1 a 3 4 0 0 0 1\n", "line 1: expected 8 finite numbers"),
        ("# nothing\n\n", "no poses"),
    ],
)
def test_bad_files_are_refused_naming_the_line(tmp_path: Path, text: str, message: str) -> None:
    path = tmp_path / "bad.txt"
    path.write_text(text)
    with pytest.raises(InputError, match=message) as err:
        read_tum(path)
    assert "bad.txt" in str(err.value) and "\n" not in str(err.value)


def test_missing_file(tmp_path: Path) -> None:
    with pytest.raises(InputError, match="cannot read trajectory"):
        read_tum(tmp_path / "none.txt")
