"""Sparse downloads: server and drones keep bit-identical replicas of the global model; a drone
without the previous replica gets the whole model; one real Flower run with them."""

from __future__ import annotations

import numpy as np
import pytest
from flwr.app import ArrayRecord, ConfigRecord, RecordDict

from dronecap.federated.downlink import (
    BASE_KEY,
    Downlink,
    apply_record,
    receive,
    replica_file,
    whole_record,
)
from dronecap.federated.fedavg import MODEL, DroneFedAvg, payload_bytes
from dronecap.federated.sparse import TABLE


def _models(rng: np.random.Generator, rounds: int) -> list[dict[str, np.ndarray]]:
    """A global model drifting over ``rounds`` rounds: a few table rows change a lot."""
    x = {TABLE: rng.normal(size=(2000, 2)).astype(np.float32), "mlp": rng.normal(size=(16, 8))}
    out = []
    for _ in range(rounds):
        x = {k: v.copy().astype(np.float32) for k, v in x.items()}
        x[TABLE][rng.choice(2000, 60, replace=False)] += rng.normal(size=(60, 2))
        x["mlp"] += 0.01 * rng.normal(size=x["mlp"].shape).astype(np.float32)
        out.append(x)
    return out


def test_replicas_stay_identical_and_a_drone_that_missed_a_round_gets_the_whole_model():
    rng = np.random.default_rng(0)
    models = _models(rng, 5)
    link = Downlink.start(models[0], rows=0.05, bits=4)
    whole, base = link.record_for("a")
    assert base == -1 and all(v.dtype == "float16" for v in whole.values())  # round 1: fp16
    drones = {d: apply_record(whole, None) for d in "ab"}
    for r, model in enumerate(models[1:], start=2):
        link.advance(model, holders={"a"} if r == 3 else {"a", "b"})  # b failed round 2
        for d in "ab":
            record, base = link.record_for(d)
            assert base == (-1 if (d == "b" and r == 3) else r - 2)
            drones[d] = apply_record(record, drones[d] if base >= 0 else None)
            for k, v in link.replica.items():
                np.testing.assert_array_equal(drones[d][k], v)  # bit-identical to the server
        change = payload_bytes(RecordDict({"a": link.record_for("a")[0]}))
        assert change < 0.2 * payload_bytes(RecordDict({"a": whole_record(link.replica)}))
    # error feedback on the server: what was not sent goes in later rounds
    gap = np.abs(link.replica[TABLE] - models[-1][TABLE]).max()
    for _ in range(8):
        link.advance(models[-1], {"a"})
    assert np.abs(link.replica[TABLE] - models[-1][TABLE]).max() < 0.05 * gap


def test_strategy_sends_holders_the_change_and_others_the_whole_model(server_task, tmp_path):
    class TwoDrones:  # what Flower's sampling asks of a Grid
        def get_node_ids(self) -> list[int]:
            return [1, 2]

    models = _models(np.random.default_rng(1), 2)
    link = Downlink.start(models[0], rows=0.05, bits=4)
    link.advance(models[1], holders={1})
    strategy = DroneFedAvg(downlink=link, min_available_nodes=2, min_train_nodes=2)
    messages = strategy.configure_train(
        2, ArrayRecord(), ConfigRecord({"run-dir": "x"}), TwoDrones()
    )
    by_node = {m.metadata.dst_node_id: m for m in messages}
    assert by_node[1].content["config"][BASE_KEY] == 0
    assert by_node[2].content["config"][BASE_KEY] == -1
    down = strategy.last_round["bytes_down"]
    assert down[1] < 0.2 * down[2]
    assert sorted(strategy.base) == sorted(MODEL + k for k in link.replica)
    # drone 1 applies the change to the replica of round 0 it kept; it keeps round 1's
    np.savez(replica_file(tmp_path, 0), **Downlink.start(models[0], 0.05, 4).replica)
    got = receive(by_node[1].content, tmp_path, 2)
    for k, v in link.replica.items():
        np.testing.assert_array_equal(got[MODEL + k], v)
    assert replica_file(tmp_path, 1).exists()
    with pytest.raises(RuntimeError, match="not kept here"):
        receive(by_node[1].content, tmp_path / "elsewhere", 2)


@pytest.mark.data
def test_simulation_with_sparse_downloads(lego_run):
    """2 lego drones, 3 rounds, drone 1 fails in round 2: in round 3 drone 0 is sent the
    change, drone 1 the whole model; each drone's copy is the global model, bit for bit."""
    from dronecap.federated.engines import run_simulated
    from dronecap.federated.state import round_file
    from dronecap.nerf.trainer import Trainer

    run = lego_run(
        2,
        rounds=3,
        quant_bits=4,
        sparse_rows=0.05,
        down_rows=0.05,
        visibility=True,
        fail_client=1,
        fail_round=2,
    )
    r0, r1, r2, r3 = run_simulated(run)
    whole = r1["bytes_down"]["0"]
    assert r1["bytes_down"]["1"] == whole  # round 1: the whole model to both
    assert r2["bytes_down"]["0"] < 0.5 * whole and r2["bytes_down"]["1"] < 0.5 * whole
    assert r3["bytes_down"]["0"] < 0.5 * whole  # drone 0 holds round 1's copy
    assert r3["bytes_down"]["1"] > 0.9 * whole  # drone 1 failed round 2: whole again
    assert r3["participants"] == 2 and np.isfinite(r3["psnr"])
    # the global model after round 2 is what both drones started round 3 from, bit for bit
    glob = Trainer.load(round_file(run / "global", 2)).model_weights()
    for k in (0, 1):
        with np.load(replica_file(run / "clients" / f"client_{k}", 2)) as mine:
            assert sorted(mine.files) == sorted(glob)
            for name in mine.files:
                np.testing.assert_array_equal(mine[name], glob[name])
