"""``kill -9`` at several points of split, shard and train: no partial output under a final
name, and a rerun completes with the same result as an uninterrupted run and no stray
temporary files. (federate: tests/federated/test_run.py.) Slow: real processes, real work."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from dronecap.datasets.format import DatasetError, open_dataset, write_dataset
from tests.reliability.conftest import complete, kill_at, random_posed, small_dataset, strays

pytestmark = pytest.mark.slow
DELAYS_S = (0.5, 1.0, 1.5, 2.5, 4.0)


@pytest.fixture(scope="module")
def big_posed(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """120 random 160x160 RGB frames (9 MB): writing it takes a while."""
    ds = random_posed(120, 5, small_dataset("posed", 3).intrinsics.scaled_to(160, 160))
    return write_dataset(tmp_path_factory.mktemp("big") / "posed.h5", ds)


def same_arrays(a: Path, b: Path) -> None:
    x, y = open_dataset(a), open_dataset(b)
    for name in ("images", "poses", "split", "near_far", "alpha"):
        u, v = getattr(x, name), getattr(y, name)
        assert (u is None and v is None) or np.array_equal(u, v), name
    assert x.shards.keys() == y.shards.keys()
    assert all(np.array_equal(x.shards[k], y.shards[k]) for k in x.shards)


def test_split_killed_anywhere_then_rerun(big_posed: Path, tmp_path: Path) -> None:
    ref, work = tmp_path / "ref", tmp_path / "work"
    ref.mkdir(), work.mkdir()
    complete(["split", str(big_posed), "-o", "dataset.h5"], ref)
    for delay in DELAYS_S:
        kill_at(["split", str(big_posed), "-o", "dataset.h5"], work, delay)
        if (work / "dataset.h5").exists():  # finished before the kill: then it is whole
            open_dataset(work / "dataset.h5")
    complete(["split", str(big_posed), "-o", "dataset.h5"], work)
    same_arrays(ref / "dataset.h5", work / "dataset.h5")
    assert not strays(work)


def test_shard_killed_anywhere_then_rerun(big_posed: Path, tmp_path: Path) -> None:
    ref, work = tmp_path / "ref", tmp_path / "work"
    ref.mkdir(), work.mkdir()
    complete(["split", str(big_posed), "-o", "dataset.h5"], ref)
    ds = ref / "dataset.h5"
    complete(["shard", str(ds), "-o", "shards", "--clients", "4"], ref)
    for delay in DELAYS_S:
        kill_at(["shard", str(ds), "-o", "shards", "--clients", "4"], work, delay)
        if (work / "shards").exists():  # a folder appears only whole
            assert len(list((work / "shards").glob("client_*.h5"))) == 4
            for p in (work / "shards").glob("client_*.h5"):
                open_dataset(p)
    complete(["shard", str(ds), "-o", "shards", "--clients", "4"], work)
    for k in range(4):
        same_arrays(ref / "shards" / f"client_{k}.h5", work / "shards" / f"client_{k}.h5")
    assert not strays(work)


def test_train_killed_anywhere_then_rerun(tmp_path: Path) -> None:
    data = write_dataset(tmp_path / "dataset.h5", small_dataset("dataset", 3))
    argv = ["train", str(data), "--preset", "test", "--steps", "120", "--checkpoint-every", "10"]
    argv += ["--threads", "1", "--no-progress"]
    complete([*argv, "--out", str(tmp_path / "ref")], tmp_path)
    run = tmp_path / "run"
    for delay in (2.0, 4.0, 6.0, 9.0, 12.0):
        kill_at([*argv, "--out", str(run)], tmp_path, delay)
        for p in run.rglob("*.h5"):
            try:
                open_dataset(p)
            except DatasetError as err:
                pytest.fail(f"partial file after kill -9: {err}")
    complete([*argv, "--out", str(run)], tmp_path)
    from dronecap.nerf.trainer import Trainer

    a = Trainer.load(tmp_path / "ref" / "checkpoint.pt")
    b = Trainer.load(run / "checkpoint.pt")
    assert a.step == b.step == 120
    wa, wb = a.model_weights(), b.model_weights()
    assert wa.keys() == wb.keys()
    assert all(np.array_equal(wa[k], wb[k]) for k in wa), "resumed model differs"
    assert not strays(run)
