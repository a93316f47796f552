"""Train/test split of posed flights: arithmetic, determinism, kept splits, errors."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from dronecap.cli import main
from dronecap.datasets.format import SPLITS, Dataset, open_dataset, write_dataset
from dronecap.datasets.split import every_kth_split, split_dataset
from dronecap.errors import InputError

TRAIN, TEST = SPLITS["train"], SPLITS["test"]


def posed_file(path: Path, source_index: np.ndarray, kind: str = "posed") -> Path:
    """A posed flight of len(source_index) 2x2 gray frames (frame value = its file position)."""
    n = len(source_index)
    images = np.arange(n, dtype=np.uint8)[:, None, None, None].repeat(2, 1).repeat(2, 2)
    ds = Dataset(images=images, kind=kind, poses=np.tile(np.eye(4), (n, 1, 1)))
    ds.source_index = np.asarray(source_index)
    return write_dataset(path, ds)


def test_paper_flight_arithmetic() -> None:
    split = every_kth_split(np.arange(1954), 8)
    # frames 0, 8, ..., 1952 go to test: 1952 / 8 + 1 = 245; 1954 - 245 = 1709
    assert int((split == TEST).sum()) == 245 and int((split == TRAIN).sum()) == 1709
    assert np.flatnonzero(split == TEST)[:3].tolist() == [0, 8, 16]


def test_split_follows_capture_order_not_file_order() -> None:
    order = np.array([50, 10, 40, 0, 30, 20])  # ranks 5, 1, 4, 0, 3, 2: even ranks to test
    assert every_kth_split(order, 2).tolist() == [TRAIN, TRAIN, TEST, TEST, TRAIN, TEST]


def test_split_dataset_writes_a_dataset(tmp_path: Path) -> None:
    rng = np.random.default_rng(3)
    src = posed_file(tmp_path / "posed.h5", rng.permutation(20) * 7)
    out = split_dataset(src, tmp_path / "dataset.h5", every=8)
    ds = open_dataset(out)
    assert ds.kind == "dataset"
    ranks = np.argsort(np.argsort(ds.source_index))
    np.testing.assert_array_equal(ds.split == TEST, ranks % 8 == 0)  # ranks 0, 8, 16: 3 tests
    assert int((ds.split == TEST).sum()) == 3
    np.testing.assert_array_equal(ds.images, open_dataset(src).images)
    assert ds.provenance["stage"] == "split" and ds.provenance["params"]["every"] == 8
    assert "posed.h5" in ds.provenance["inputs"]
    # deterministic: a second run gives the same split
    again = open_dataset(split_dataset(src, tmp_path / "again.h5", every=8))
    np.testing.assert_array_equal(again.split, ds.split)


def test_existing_split_is_kept(tmp_path: Path) -> None:
    src = posed_file(tmp_path / "in.h5", np.arange(6), kind="dataset")
    ds = open_dataset(src)
    ds.split = np.array([0, 1, 2, 0, 0, 2], np.int8)
    write_dataset(src, ds)
    out = open_dataset(split_dataset(src, tmp_path / "out.h5", every=2))
    assert out.split.tolist() == [0, 1, 2, 0, 0, 2]
    assert out.provenance["params"]["kept_existing_split"] is True


@pytest.mark.parametrize("case", ["every1", "one_frame", "frames_kind", "no_poses", "missing"])
def test_bad_requests(tmp_path: Path, case: str) -> None:
    src = tmp_path / "posed.h5"
    every = 8
    if case == "every1":
        posed_file(src, np.arange(10))
        every = 1
    elif case == "one_frame":
        posed_file(src, np.arange(1))
    elif case == "frames_kind":
        posed_file(src, np.arange(10), kind="frames")
    elif case == "no_poses":
        write_dataset(src, Dataset(images=np.zeros((4, 2, 2, 1), np.uint8), kind="posed"))
    out = tmp_path / "dataset.h5"
    with pytest.raises(InputError) as err:
        split_dataset(src, out, every=every)
    assert "\n" not in str(err.value)
    assert not out.exists()


def test_cli_uses_workspace_names(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    posed_file(tmp_path / "posed.h5", np.arange(16))
    assert main(["split", "--workdir", str(tmp_path)]) == 0
    assert "14 train" in capsys.readouterr().out
    assert open_dataset(tmp_path / "dataset.h5").split.tolist().count(TEST) == 2
    assert main(["split", "--workdir", str(tmp_path / "empty")]) == 1
    assert "posed.h5" in capsys.readouterr().err


def test_lego_keeps_its_official_split(lego_h5: Path, tmp_path: Path) -> None:
    out = open_dataset(split_dataset(lego_h5, tmp_path / "d.h5"))
    np.testing.assert_array_equal(out.split, open_dataset(lego_h5).split)
