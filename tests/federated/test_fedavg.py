"""FedAvg maths and byte accounting on hand-made tensors (no Flower run, no training)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from flwr.app import Message, MessageType, MetricRecord, RecordDict
from flwr.serverapp.strategy.strategy_utils import aggregate_arrayrecords

from dronecap.datasets.format import Dataset, Intrinsics, write_dataset
from dronecap.federated.fedavg import (
    CODEC,
    WEIGHT_KEY,
    DroneFedAvg,
    array_data_bytes,
    from_record,
    pack_update,
    payload_bytes,
    to_record,
    unpack_update,
    weighted_mean,
)
from dronecap.nerf.config import preset


def _reply(update: dict[str, np.ndarray], n_images: int, compress: bool = False) -> RecordDict:
    return RecordDict(
        {
            "arrays": to_record(update, compress),
            "metrics": MetricRecord({WEIGHT_KEY: n_images}),
        }
    )


def test_weighted_mean_by_image_count():
    a = {"w": np.array([0.0, 2.0], np.float32), "b": np.array([[1.0]], np.float32)}
    b = {"w": np.array([4.0, 6.0], np.float32), "b": np.array([[5.0]], np.float32)}
    # weights 1 and 3: (0*1 + 4*3)/4 = 3, (2 + 18)/4 = 5, (1 + 15)/4 = 4
    m = weighted_mean([a, b], [1, 3])
    np.testing.assert_allclose(m["w"], [3.0, 5.0])
    np.testing.assert_allclose(m["b"], [[4.0]])
    # equal shards: the arithmetic mean (the paper's case)
    np.testing.assert_allclose(weighted_mean([a, b], [25, 25])["w"], [2.0, 4.0])


def test_flower_fedavg_matches_reference_on_packed_updates():
    rng = np.random.default_rng(0)
    updates = [
        {"encoding.table": rng.normal(size=(7, 2)), "mlp.0.weight": rng.normal(size=(3, 4))}
        for _ in range(3)
    ]
    counts = [25, 25, 50]
    replies = [_reply(pack_update(u, None), n) for u, n in zip(updates, counts, strict=True)]
    model, grid = unpack_update(from_record(aggregate_arrayrecords(replies, WEIGHT_KEY)))
    ref = weighted_mean(updates, counts)
    assert grid == {}
    for k in ref:
        np.testing.assert_allclose(model[k], ref[k], rtol=1e-5, atol=1e-6)
        assert model[k].dtype == np.float32


def test_grid_kept_local_unless_exchanged():
    model = {"t": np.ones((4, 2), np.float32)}
    grid = {"density": np.array([0.0, 0.5, 0.02], np.float32), "occupied": np.ones(3, bool)}
    local = pack_update(model, None)
    assert sorted(local) == ["model/t"]
    shared = pack_update(model, grid)
    # densities travel, occupancy bits (derived data) do not
    assert sorted(shared) == ["grid/density", "model/t"]
    m, g = unpack_update(shared)
    np.testing.assert_array_equal(m["t"], model["t"])
    np.testing.assert_array_equal(g["density"], grid["density"])
    with pytest.raises(KeyError):
        unpack_update({"optimizer/exp_avg": np.zeros(2)})


def test_fp16_transfer_halves_the_data_and_rounds_to_half_precision():
    x = {"t": np.array([1.0, 1.0 + 2**-12, 3.14159], np.float32)}
    p32, p16 = pack_update(x, None, "fp32"), pack_update(x, None, "fp16")
    assert p16["model/t"].dtype == np.float16
    assert array_data_bytes(p32) == 12 and array_data_bytes(p16) == 6
    back, _ = unpack_update(p16)
    # 1 + 2^-12 is below half an fp16 ulp at 1 (2^-11) -> 1; pi -> 3.140625 (fp16 grid 2^-9)
    np.testing.assert_array_equal(back["t"], np.array([1.0, 1.0, 3.140625], np.float32))
    with pytest.raises(ValueError):
        pack_update(x, None, "int8")


def test_payload_bytes_counts_every_serialised_byte_of_the_arrays():
    n = 1000
    one = {"t": np.zeros(n, np.float32)}
    two = {"t": np.zeros(n, np.float32), "u": np.ones(n, np.float32)}
    b32 = payload_bytes(_reply(pack_update(one, None, "fp32"), 1))
    b16 = payload_bytes(_reply(pack_update(one, None, "fp16"), 1))
    # Same headers (the .npy header is padded to 128 bytes either way): exactly 2 bytes/value less
    assert b32 - b16 == 2 * n
    # A second array of n fp32 values adds its 4n data bytes plus bounded header overhead
    extra = payload_bytes(_reply(pack_update(two, None, "fp32"), 1)) - b32
    assert 4 * n <= extra <= 4 * n + 1000


def test_tiny_dronerf_payload_without_grid_in_fp16():
    """The hash table (16 levels x 8192 rows x 2, level 0 dense with 17^3 rows) + MLPs."""
    from dronecap.nerf.hashgrid import level_offsets, level_resolutions

    cfg = preset("tiny-dronerf")
    rows = level_offsets(level_resolutions(cfg.levels, cfg.n_min, cfg.n_max), cfg.log2_hashmap)[-1]
    assert rows == 17**3 + 15 * 8192  # level 0 is indexed densely
    h = cfg.hidden
    shapes = {
        "encoding.table": (rows, 2),
        "density_mlp.0.weight": (h, 32),
        "density_mlp.2.weight": (16, h),
        "color_mlp.0.weight": (h, 32),
        "color_mlp.2.weight": (h, h),
        "color_mlp.4.weight": (3, h),
    }
    # distinct random values: identical arrays would be sent once (Flower dedups objects)
    rng = np.random.default_rng(0)
    model = {k: rng.normal(size=s).astype(np.float32) for k, s in shapes.items()}
    values = rows * 2 + h * 32 * 2 + 16 * h + h * h + 3 * h
    up = payload_bytes(_reply(pack_update(model, None, "fp16"), 25))
    assert 2 * values <= up <= 2 * values + 4000  # data + headers (~500 B per array)
    assert up < 0.54e6


@pytest.mark.parametrize(
    "array",
    [
        np.array([0.0, -0.0, np.inf, -np.inf, np.nan, 65504.0, 6e-8], np.float16),
        np.arange(24, dtype=np.float32).reshape(2, 3, 4) * 1e-3,
        np.zeros((0, 2), np.float16),
        np.array([[True, False, True]]),
        np.array([-(2**62), 2**62], np.int64),
    ],
)
def test_compressed_arrays_round_trip_bit_exactly(array):
    rec = to_record({"a": array}, compress=True)
    assert rec["a"].stype == CODEC
    back = from_record(rec)["a"]
    assert back.dtype == array.dtype and back.shape == array.shape
    assert back.tobytes() == array.tobytes()  # bit-exact, NaN payload and signed zero included


def test_compression_shrinks_hash_table_like_fp16_values():
    """Small-magnitude fp16 values (a trained table's entries) share few sign/exponent bytes."""
    rng = np.random.default_rng(0)
    table = {"encoding.table": (rng.normal(size=(50_000, 2)) * 0.05).astype(np.float32)}
    plain = payload_bytes(_reply(pack_update(table, None, "fp16"), 25))
    packed = payload_bytes(_reply(pack_update(table, None, "fp16"), 25, compress=True))
    assert packed < 0.9 * plain
    # pure noise bytes cannot shrink: deflate's overhead stays bounded
    noise = {"n": rng.integers(0, 2**16, 50_000).astype(np.uint16).view(np.float16)}
    n_plain = payload_bytes(_reply(noise, 1))
    assert payload_bytes(_reply(noise, 1, compress=True)) <= n_plain * 1.01 + 100


def test_union_of_shards_keeps_every_train_frame(tmp_path):
    from dronecap.federated.baselines import union_train

    k = Intrinsics(10.0, 10.0, 2.0, 2.0, 4, 4)

    def shard(value: int, n_train: int) -> str:
        n = n_train + 1
        ds = Dataset(
            images=np.full((n, 4, 4, 3), value, np.uint8),
            kind="shard",
            poses=np.tile(np.eye(4), (n, 1, 1)),
            intrinsics=k,
            split=np.array([0] * n_train + [2], np.int8),
            aabb=np.array([[-1.0, -1, -1], [1, 1, 1]]),
        )
        p = tmp_path / f"client_{value}.h5"
        write_dataset(p, ds)
        return str(p)

    u = union_train([shard(1, 2), shard(2, 3)])
    assert u.n == 5
    assert [int(im[0, 0, 0]) for im in u.images] == [1, 1, 2, 2, 2]
    assert (u.split == 0).all() and u.poses.shape == (5, 4, 4)
    assert dataclasses.replace(u).intrinsics == k


def test_rebuilt_grid_hides_less_than_one_probe_per_cell(cube_rgb):
    """A grid rebuilt from a trained model alone (the global model's, a joining drone's)
    renders closer to what the model renders with no empty-space skipping than a grid from
    one probe per cell does, and about as close as the grid training maintained."""
    import torch

    from dronecap.federated.run import rebuild_grid
    from dronecap.nerf import occupancy
    from dronecap.nerf.trainer import Trainer

    tr = Trainer(preset("test").replace(grid_res=16, steps=600), cube_rgb)
    tr.train(600)
    pose, k = cube_rgb.poses[1], cube_rgb.intrinsics
    trained = tr.grid
    # every cell of the visual hull occupied: nothing the model may render there is skipped
    tr.grid = occupancy.restrict(occupancy.init_state(tr.grid_cfg), trained.allowed)
    full = tr.render(pose, k)
    tr.grid = trained
    kept = float(abs(tr.render(pose, k) - full).mean())

    def error(passes: int) -> float:
        tr.generator = torch.Generator().manual_seed(0)
        rebuild_grid(tr, passes)
        assert tr.grid.occupied.float().mean() < 0.5  # empty space is skipped
        return float(abs(tr.render(pose, k) - full).mean())

    once, many = error(1), error(16)
    assert many < 0.8 * once
    assert many < 1.1 * kept


def test_rebuilt_grid_stays_inside_the_trainers_visual_hull(cube_rgb):
    """A rebuilt grid keeps the cells the trainer may ever occupy (its views' visual hull):
    none outside them is occupied, whatever the model's densities there."""
    import torch

    from dronecap.federated.run import rebuild_grid
    from dronecap.nerf import occupancy
    from dronecap.nerf.trainer import Trainer

    tr = Trainer(preset("test").replace(grid_res=16, steps=100), cube_rgb)
    tr.train(100)
    res = tr.grid_cfg.res
    hull = torch.arange(res**3) // (res * res) < res // 2  # cells of the lower half in x
    tr.grid = occupancy.restrict(tr.grid, hull)
    rebuild_grid(tr)
    assert tr.grid.allowed is not None and torch.equal(tr.grid.allowed, hull)
    assert tr.grid.occupied[hull].any() and not tr.grid.occupied[~hull].any()


def _replies(updates: list[dict[str, np.ndarray]], counts: list[int]) -> list[Message]:
    """Replies of drones 1..K to a train instruction, as the server receives them (fp16)."""
    out = []
    for node, (u, n) in enumerate(zip(updates, counts, strict=True), start=1):
        ask = Message(RecordDict(), dst_node_id=node, message_type=MessageType.TRAIN)
        out.append(Message(_reply(pack_update(u, None, "fp16"), n), reply_to=ask))
    return out


def test_server_momentum_step_and_resume(server_task):
    """FedAvgM: x <- x - lr * m, m <- beta * m + (x - avg); a resumed strategy continues it."""
    rng = np.random.default_rng(1)
    x0 = {"model/t": rng.normal(size=(5, 2)).astype(np.float32)}
    lr, beta, counts = 1.5, 0.5, [25, 75]
    rounds = [[{"t": rng.normal(size=(5, 2))} for _ in counts] for _ in range(3)]

    def averaged(r: int) -> np.ndarray:  # what the server averages: the fp16 updates
        ups = [{"t": u["t"].astype(np.float16)} for u in rounds[r]]
        return weighted_mean(ups, counts)["t"]

    strategy = DroneFedAvg(server_learning_rate=lr, server_momentum=beta)
    strategy.resume(x0, {})
    x, m = x0["model/t"].astype(np.float64), None
    for r in range(2):
        agg, _ = strategy.aggregate_train(r + 1, _replies(rounds[r], counts))
        g = x - averaged(r)
        m = g if m is None else beta * m + g
        x = x - lr * m
        np.testing.assert_allclose(from_record(agg)["model/t"], x, rtol=1e-5, atol=1e-5)
    # plain FedAvg would land on the average itself: the server step moved it
    assert np.abs(x - averaged(1)).max() > 0.1
    resumed = DroneFedAvg(server_learning_rate=lr, server_momentum=beta)
    resumed.resume(from_record(agg), strategy.server_state())
    a, _ = strategy.aggregate_train(3, _replies(rounds[2], counts))
    b, _ = resumed.aggregate_train(3, _replies(rounds[2], counts))
    np.testing.assert_array_equal(from_record(a)["model/t"], from_record(b)["model/t"])


def test_default_server_step_is_plain_fedavg(server_task):
    rng = np.random.default_rng(2)
    updates = [{"t": rng.normal(size=(4,))} for _ in range(2)]
    strategy = DroneFedAvg()
    strategy.resume({"model/t": np.zeros(4, np.float32)}, {})
    agg, _ = strategy.aggregate_train(1, _replies(updates, [25, 25]))
    ref = weighted_mean([{"t": u["t"].astype(np.float16)} for u in updates], [25, 25])["t"]
    np.testing.assert_allclose(from_record(agg)["model/t"], ref, rtol=1e-6)
    assert strategy.server_state() == {}


def test_each_drone_keeps_its_own_exposures_through_a_round(make_cube, tmp_path):
    """Camera footage (no alpha): the photometric model is on, yet no exposure or vignetting
    parameter travels, and installing the averaged global model leaves each drone's own
    per-frame gains (different frame counts per drone) untouched."""
    import torch

    from dronecap.federated.run import install_global
    from dronecap.nerf.trainer import Trainer

    drones = []
    for k, n in enumerate((12, 8)):
        ds = dataclasses.replace(make_cube(n=n, size=16), alpha=None)
        tr = Trainer(preset("test").replace(learn_exposure="auto", seed=k), ds)
        tr.train(6)
        assert tr.cfg.learn_exposure == "on" and tr.photometric.log_gain.abs().sum() > 0
        drones.append(tr)
    updates = [pack_update(tr.model_weights(), None) for tr in drones]
    assert not any("gain" in key or "vignette" in key for key in updates[0])
    own = [{k: v.clone() for k, v in tr.photometric.state_dict().items()} for tr in drones]
    mean = weighted_mean(updates, [9.0, 6.0])
    for tr, mine in zip(drones, own, strict=True):
        install_global(tr, mean, rebuild=False)
        for name, value in tr.photometric.state_dict().items():
            torch.testing.assert_close(value, mine[name], rtol=0, atol=0)


def test_union_of_a_swarms_drone_shards_keeps_each_frames_camera(tmp_path):
    """Drone shards (a camera per drone): the centralized baseline's train set keeps every
    frame's camera and drone; shards with other camera tables are refused."""
    from dronecap.errors import InputError
    from dronecap.federated.baselines import union_train

    cams = [Intrinsics(10.0, 10.0, 2.0, 2.0, 4, 4), Intrinsics(11.0, 11.0, 2.0, 2.0, 4, 4)]

    def shard(drone: int, n_train: int, cameras: list) -> str:
        n = n_train + 1
        ds = Dataset(
            images=np.full((n, 4, 4, 1), drone, np.uint8),
            kind="shard",
            poses=np.tile(np.eye(4), (n, 1, 1)),
            split=np.array([0] * n_train + [2], np.int8),
            aabb=np.array([[-1.0, -1, -1], [1, 1, 1]]),
        )
        ds.drone = np.full(n, drone, np.int16)
        ds.drone_names = ["a", "b"]
        ds.set_cameras(cameras, np.full(n, drone))
        p = tmp_path / f"client_{drone}_{len(cameras)}.h5"
        write_dataset(p, ds)
        return str(p)

    u = union_train([shard(0, 2, cams), shard(1, 3, cams)])
    assert u.n == 5 and u.drones().tolist() == [0, 0, 1, 1, 1]
    assert [u.camera_of(i).fx for i in range(5)] == [10.0, 10.0, 11.0, 11.0, 11.0]
    with pytest.raises(InputError, match="another camera table"):
        union_train([shard(0, 2, cams), shard(1, 3, cams[::-1])])


def test_table_step_mean_takes_the_drones_change_and_steps_the_mlps(server_task):
    """``table_step="mean"``: the hash table lands on the mean of the drones' tables (a row one
    drone saw is that drone's change), while the MLPs still take FedAvgM's server step."""
    rng = np.random.default_rng(3)
    x0 = {
        "model/encoding.table": np.zeros((6, 2), np.float32),
        "model/mlp": np.zeros(3, np.float32),
    }
    updates = [{"encoding.table": rng.normal(size=(6, 2)), "mlp": rng.normal(size=3)} for _ in "ab"]
    ref = weighted_mean([{k: v.astype(np.float16) for k, v in u.items()} for u in updates], [1, 1])
    out = {}
    for step in ("mean", "server"):
        strategy = DroneFedAvg(server_learning_rate=2.0, server_momentum=0.5, table_step=step)
        strategy.resume(x0, {})
        agg, _ = strategy.aggregate_train(1, _replies(updates, [10, 10]))
        out[step] = from_record(agg)
    np.testing.assert_allclose(
        out["mean"]["model/encoding.table"], ref["encoding.table"], atol=1e-6
    )
    np.testing.assert_allclose(
        out["server"]["model/encoding.table"], 2 * ref["encoding.table"], atol=1e-5
    )
    for step in out:  # the MLPs: x - lr * (x - avg) = 2 * avg from x = 0
        np.testing.assert_allclose(out[step]["model/mlp"], 2 * ref["mlp"], atol=1e-5)
