"""Checked and compressed updates: the sparse quantised codec, error feedback, the checks a
reply passes before it is averaged, and visibility-weighted averaging; one real Flower
simulation with three hostile drones."""

from __future__ import annotations

import numpy as np
import pytest
from flwr.app import Array, ArrayRecord, Message, MessageType, MetricRecord, RecordDict

from dronecap.federated.checks import screen
from dronecap.federated.fedavg import (
    WEIGHT_KEY,
    DroneFedAvg,
    from_record,
    masked_mean,
    pack_update,
    to_record,
)
from dronecap.federated.sparse import (
    TABLE,
    decode_delta,
    encode_delta,
    encode_update,
    select_rows,
)


@pytest.mark.parametrize("bits", [8, 4])
def test_sparse_delta_round_trip_sends_the_largest_rows(bits):
    rng = np.random.default_rng(0)
    d = rng.normal(size=(500, 2)).astype(np.float32) * 1e-3
    d[[3, 77, 499]] = [[1.0, -2.0], [0.5, 0.5], [-3.0, 0.1]]  # the three largest rows
    rows = select_rows(d, 3 / 500)
    assert rows.tolist() == [3, 77, 499]
    arr, sent = encode_delta(d, rows, bits)
    back, mask = decode_delta(arr)
    np.testing.assert_array_equal(back, sent)  # the sender knows exactly what arrives
    assert np.flatnonzero(mask).tolist() == [3, 77, 499] and not back[~mask].any()
    tol = 3.0 / (2 ** (bits - 1) - 1)  # half a step of the block's scale, and fp16 scales
    assert np.abs(back[rows] - d[rows]).max() <= tol
    assert len(arr.data) < 60  # 3 rows: a header, 3 row numbers, 6 codes, 1 scale, deflated


def test_malformed_sparse_arrays_are_refused():
    d = np.ones((10, 2), np.float32)
    arr, _ = encode_delta(d, np.array([1, 4]), 8)
    truncated = Array(dtype="float32", shape=(10, 2), stype=arr.stype, data=arr.data[:-3])
    other_shape = Array(dtype="float32", shape=(3, 2), stype=arr.stype, data=arr.data)
    for bad in (truncated, other_shape):
        with pytest.raises(ValueError):
            decode_delta(bad)


@pytest.mark.parametrize("mlp_bits", [8, 4])
def test_error_feedback_loses_nothing_over_rounds(mlp_bits):
    """What a drone sent over the rounds plus its residual equals its true total change, the
    MLPs at 8 or 4 bits (the default) as well as the table."""
    rng = np.random.default_rng(1)
    received = {TABLE: np.zeros((400, 2), np.float32), "mlp": np.zeros((8, 4), np.float32)}
    residual: dict[str, np.ndarray] = {}
    total_true = {k: np.zeros_like(v, np.float64) for k, v in received.items()}
    total_sent = {k: np.zeros_like(v, np.float64) for k, v in received.items()}
    for _ in range(5):
        local = {k: v + rng.normal(size=v.shape).astype(np.float32) for k, v in received.items()}
        arrays, residual = encode_update(local, received, residual, 0.05, 4, mlp_bits)
        assert arrays["mlp"].data[0] == mlp_bits  # the header's first byte: the bits
        for k in received:
            total_true[k] += local[k] - received[k]
            total_sent[k] += decode_delta(arrays[k])[0]
        assert decode_delta(arrays[TABLE])[1].sum() == 20  # 5 % of the table's rows
    for k in received:
        np.testing.assert_allclose(total_sent[k] + residual[k], total_true[k], atol=1e-4)


def test_screen_leaves_out_nan_huge_miscounted_and_misshapen_updates():
    rng = np.random.default_rng(2)
    ref = {"t": rng.normal(size=(6, 2)).astype(np.float32)}
    honest = [{"t": ref["t"] + 0.01 * rng.normal(size=(6, 2)).astype(np.float32)} for _ in range(3)]
    nan = {"t": honest[0]["t"].copy()}
    nan["t"][2, 1] = np.nan
    updates = {
        1: honest[0],
        2: honest[1],
        3: honest[2],
        4: nan,
        5: {"t": np.full((6, 2), 1e30, np.float32)},
        6: honest[0],  # claims 10^9 images
        7: {"t": ref["t"][:5]},
        8: {"t": ref["t"].astype(np.int32)},
        9: {"t": ref["t"] + 50.0},  # finite, in range, but a change far beyond the others'
    }
    claimed = {k: 25 for k in updates} | {6: 1e9}
    out = screen(updates, ref, claimed, {k: 25 for k in updates})
    assert sorted(out) == [4, 5, 6, 7, 8, 9]
    assert "non-finite" in out[4] and "magnitude 1e+30" in out[5]
    assert "claims 1e+09 train images, its shard holds 25" == out[6]
    assert "shape" in out[7] and "dtype int32" in out[8] and "median" in out[9]


def test_visibility_weighting_does_not_dilute_rows_one_drone_saw():
    d1 = {"t": np.array([[1.0], [2.0]])}
    d2 = {"t": np.array([[3.0], [0.0]])}  # drone 2 did not send row 1
    masks = {1: {"t": np.array([True, True])}, 2: {"t": np.array([True, False])}}
    plain = masked_mean({1: d1, 2: d2}, {1: 1.0, 2: 1.0}, {})
    vis = masked_mean({1: d1, 2: d2}, {1: 1.0, 2: 1.0}, masks)
    np.testing.assert_allclose(plain["t"][:, 0], [2.0, 1.0])
    np.testing.assert_allclose(vis["t"][:, 0], [2.0, 2.0])  # row 1: drone 1's change alone
    zero = masked_mean({1: d1, 2: d2}, {1: 0.0, 2: 0.0}, {})  # no ZeroDivisionError: equal
    np.testing.assert_allclose(zero["t"], plain["t"])


def _reply(node: int, arrays, n: float) -> Message:
    ask = Message(RecordDict(), dst_node_id=node, message_type=MessageType.TRAIN)
    content = RecordDict({"arrays": arrays, "metrics": MetricRecord({WEIGHT_KEY: n})})
    return Message(content, reply_to=ask)


def test_strategy_averages_the_honest_drones_and_logs_the_others(server_task):
    rng = np.random.default_rng(3)
    x0 = {"model/" + TABLE: rng.normal(size=(50, 2)).astype(np.float32)}
    strategy = DroneFedAvg()
    strategy.resume(x0, {})
    strategy.known_examples = {1: 25, 2: 25, 3: 25, 4: 25, 5: 25}
    local = {TABLE: x0["model/" + TABLE] + 0.1}
    sparse, _ = encode_update(local, {TABLE: x0["model/" + TABLE]}, {}, rows=1.0, bits=8)
    bad = pack_update({TABLE: np.full((50, 2), np.nan, np.float32)}, None)
    s = sparse[TABLE]
    truncated = Array(dtype=s.dtype, shape=tuple(s.shape), stype=s.stype, data=s.data[:-4])
    replies = [
        _reply(1, ArrayRecord({"model/" + TABLE: sparse[TABLE]}), 25),
        _reply(2, to_record(bad), 25),
        _reply(3, to_record(pack_update(local, None)), 10**9),
        _reply(4, to_record(pack_update({TABLE: np.zeros((3, 2), np.float32)}, None)), 25),
        _reply(5, ArrayRecord({"model/" + TABLE: truncated}), 25),
    ]
    agg, _ = strategy.aggregate_train(1, replies)
    failed = strategy.last_round["failed"]
    assert sorted(failed) == [2, 3, 4, 5] and failed[5].startswith("unreadable update")
    got = from_record(agg)["model/" + TABLE]
    np.testing.assert_allclose(got, local[TABLE], atol=2e-3)  # drone 1's 8-bit update alone


@pytest.mark.data
def test_simulation_leaves_out_nan_huge_and_miscounted_drones(lego_run):
    """A real Flower round (4 lego drones, sparse 4-bit updates): drones 1-3 send a NaN, a 1e30
    model and a claim of 10^9 images; they are left out with their reasons, the round
    completes with drone 0's update and a finite model."""
    from dronecap.federated.engines import run_simulated

    run = lego_run(
        4,
        rounds=1,
        quant_bits=4,
        sparse_rows=0.05,
        visibility=True,
        poison={"1": "nan", "2": "huge", "3": "count"},
    )
    r0, r1 = run_simulated(run)
    assert r1["participants"] == 1 and sorted(r1["bytes_up"]) == ["0", "1", "2", "3"]
    failed = r1["failed"]
    assert sorted(failed) == ["1", "2", "3"]
    assert "non-finite" in failed["1"] and "magnitude 1e+30" in failed["2"]
    assert failed["3"].startswith("claims 1e+09 train images")
    assert np.isfinite(r1["psnr"])
    # the honest sparse update is a fraction of the poisoned drones' whole fp32 models
    assert r1["bytes_up"]["0"] < 0.2 * r1["bytes_up"]["1"]
    assert (run / "clients" / "client_0" / "residual_001.npz").exists()
