"""Real Flower runs (simulation engine, Ray) of Tiny-DroNeRF FedAvg on lego shards.

The default suite holds ONE simulation (2 drones, `test` preset, a fault injected in round 2);
the CLI end to end with baselines and an interruption + resume is marked slow.
"""

from __future__ import annotations

import dataclasses
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import torch

from dronecap.nerf.config import preset

SMALL = dict(pretrain=12, local_steps=6, rounds=2, eval_views=2)


@pytest.fixture(scope="module")
def lego_h5(lego_dir, tmp_path_factory) -> Path:
    """The real lego scene at 160 px as dataset.h5 (import takes ~1 s)."""
    from dronecap.datasets.blender import import_blender

    return import_blender(lego_dir, tmp_path_factory.mktemp("lego") / "dataset.h5", progress=False)


@pytest.fixture(scope="module")
def lego_shards(lego_h5, tmp_path_factory) -> list[str]:
    """Two IID shards of lego (50 train images each + the 200 common test views)."""
    from dronecap.datasets.shard import shard_dataset

    out = shard_dataset(lego_h5, tmp_path_factory.mktemp("shards") / "shards", 2, "iid")
    return [str(out / f"client_{k}.h5") for k in range(2)]


@pytest.mark.data
def test_simulation_two_drones_with_a_failing_client(lego_shards, tmp_path):
    from flwr.app import RecordDict

    from dronecap.federated.engines import run_simulated
    from dronecap.federated.fedavg import pack_update, payload_bytes, to_record
    from dronecap.federated.state import FedSettings, round_file, save_settings
    from dronecap.nerf.trainer import Trainer

    run = tmp_path / "run"
    s = FedSettings(
        shards=lego_shards,
        cfg=dataclasses.asdict(preset("test")),
        fail_client=1,
        fail_round=2,
        compress=True,  # lossless: the exact-equality checks below hold through it
        **SMALL,
    )
    save_settings(run, s)
    rounds = run_simulated(run)

    assert [r["round"] for r in rounds] == [0, 1, 2]
    assert [r["steps"] for r in rounds] == [12, 18, 24]  # N_pt + r N_l
    r0, r1, r2 = rounds
    # round 0: the coordinator alone pretrained and uploaded the initial global model
    assert list(r0["bytes_up"]) == ["0"] and r0["participants"] == 1
    # round 1: both drones got the global model and sent updates of about the same
    # (compressed) size, smaller than the same arrays sent plain
    assert r1["participants"] == 2 and r1["failed"] == {}
    up0, up1 = r1["bytes_up"]["0"], r1["bytes_up"]["1"]
    assert abs(up0 - up1) < 0.02 * up0
    assert r1["bytes_down"]["0"] == r1["bytes_down"]["1"] > 0
    mine1 = Trainer.load(round_file(run / "clients" / "client_0", 1)).model_weights()
    plain = payload_bytes(RecordDict({"arrays": to_record(pack_update(mine1, None))}))
    assert up0 < plain
    # round 2: drone 1 raised; it is left out of the average, logged, and the run went on
    assert r2["participants"] == 1 and list(r2["bytes_up"]) == ["0"]
    assert "injected fault: client 1 fails in round 2" in r2["failed"]["1"]
    assert set(r2["bytes_down"]) == {"0", "1"}  # it was sent the model all the same
    for r in rounds:
        assert np.isfinite(r["psnr"]) and r["psnr"] > 5
    # non-averaged state on disk, per drone per round (drone 1 has none for its failed round)
    clients = run / "clients"
    assert sorted(p.name for p in (clients / "client_0").iterdir()) == [
        "round_000.pt",
        "round_001.pt",
        "round_002.pt",
    ]
    assert sorted(p.name for p in (clients / "client_1").iterdir()) == ["round_001.pt"]
    # drone 1 joined at round 1 on the coordinator's schedule: N_pt + N_l steps
    assert Trainer.load(round_file(clients / "client_1", 1)).step == 18
    # the occupancy grid stayed local: the drones' grids differ after round 1
    g0 = Trainer.load(round_file(clients / "client_0", 1)).grid_state()["density"]
    g1 = Trainer.load(round_file(clients / "client_1", 1)).grid_state()["density"]
    assert not np.array_equal(g0, g1)
    # the final global model is an ordinary checkpoint: round 2's global model, testable
    final = Trainer.load(run / "checkpoint.pt")
    glob2 = Trainer.load(round_file(run / "global", 2))
    w, v = final.model_weights(), glob2.model_weights()
    assert all(np.array_equal(w[k], v[k]) for k in w)
    # round 2's global model is drone 0's update alone (the only one averaged)
    mine = Trainer.load(round_file(clients / "client_0", 2)).model_weights()
    assert all(np.array_equal(w[k], mine[k]) for k in w)
    doc = json.loads((run / "rounds.json").read_text())
    assert doc["settings"]["fail_client"] == 1
    # the global model's grid was rebuilt inside every drone's visual hull (sent at discovery)
    from dronecap.federated.state import train_split

    hulls = [Trainer(s.train_config(), train_split(p)).grid.allowed for p in lego_shards]
    occupied = torch.from_numpy(glob2.grid_state()["occupied"]).reshape(hulls[0].shape)
    assert occupied.any() and not (occupied & ~(hulls[0] & hulls[1])).any()


TABLE = "model/encoding.table"


def _check_server_momentum_step(run: Path, rounds: int, lr: float, beta: float) -> None:
    """Every round's global model is FedAvgM's step from the previous one, across the resume:
    ``m_r = beta m_{r-1} + (x_{r-1} - avg_r)``, ``x_r = x_{r-1} - lr m_r``, with ``avg_r`` the
    mean of the drones' fp16 models (equal shards) and ``m_r`` as saved after round r; the hash
    table takes the drones' mean itself (``--table-step mean``, the default): ``m_r`` 0 there
    and ``x_r = avg_r``."""
    from dronecap.federated.state import load_momentum, round_file
    from dronecap.nerf.trainer import Trainer

    def weights(path: Path) -> dict[str, np.ndarray]:
        return {f"model/{k}": v for k, v in Trainer.load(path).model_weights().items()}

    x = weights(round_file(run / "global", 0))
    m: dict[str, np.ndarray] = {}
    for r in range(1, rounds + 1):
        drones = [weights(round_file(run / "clients" / f"client_{k}", r)) for k in range(2)]
        saved = load_momentum(run, r)
        assert sorted(saved) == sorted(x)
        avg = {
            k: np.mean([d[k].astype(np.float16).astype(np.float64) for d in drones], axis=0)
            for k in x
        }
        for key in x:
            m_r = (beta * m[key] if m else 0.0) + (x[key] - avg[key])
            # one fp16 step of weights below 0.25 (2^-13): what the drones sent can round
            # one step away from their saved float32 weights cast here
            np.testing.assert_allclose(saved[key], 0.0 if key == TABLE else m_r, atol=1.3e-4)
        m = saved
        new = weights(round_file(run / "global", r))
        for key in x:
            want = avg[key] if key == TABLE else x[key] - lr * m[key]
            np.testing.assert_allclose(new[key], want, atol=1e-3 if key == TABLE else 1e-4)
        x = new


def _federate(args: list[str], **kw) -> subprocess.Popen:
    cmd = [sys.executable, "-m", "dronecap.cli", "federate", *args]
    return subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, **kw)


@pytest.mark.slow
@pytest.mark.data
def test_cli_interrupted_run_resumes_from_last_round(lego_h5, tmp_path):
    out = tmp_path / "fed"
    args = [str(lego_h5), "--clients", "2", "--scheme", "sector", "--preset", "test"]
    args += ["--pretrain", "12", "--local-steps", "6", "--rounds", "3", "--eval-views", "1"]
    args += ["--transfer-dtype", "fp16", "--compress", "--quant-bits", "0", "--server-lr", "1.5"]
    args += ["--server-momentum", "0.5", "--out", str(out)]
    # first attempt: stopped hard (whole process group) once round 1 is recorded
    proc = _federate(args, start_new_session=True)
    rounds_json = out / "rounds.json"
    deadline = time.time() + 600
    while time.time() < deadline and proc.poll() is None:
        if rounds_json.exists() and len(json.loads(rounds_json.read_text())["rounds"]) >= 2:
            break
        time.sleep(0.5)
    os.killpg(proc.pid, signal.SIGKILL)
    proc.wait()
    before = json.loads(rounds_json.read_text())["rounds"]
    assert 2 <= len(before) <= 3
    # second attempt resumes after the last completed round, with --baselines this time
    proc = _federate([*args, "--baselines"])
    text = proc.communicate(timeout=900)[0]
    assert proc.returncode == 0, text
    assert f"resuming after round {len(before) - 1} of 3" in text
    doc = json.loads(rounds_json.read_text())
    assert [r["round"] for r in doc["rounds"]] == [0, 1, 2, 3]
    assert doc["rounds"][: len(before)] == before  # completed rounds were not redone
    assert sorted(doc["baselines"]) == ["centralized", "client_0", "client_1"]
    assert [c["steps"] for c in doc["baselines"]["centralized"]] == [12, 18, 24, 30]
    assert (out / "psnr.png").stat().st_size > 1000
    _check_server_momentum_step(out, rounds=3, lr=1.5, beta=0.5)
    # the same run folder with other settings is refused, not silently mixed
    proc = _federate([*args[:-2], "--rounds", "4", "--out", str(out)])
    text = proc.communicate(timeout=300)[0]
    assert proc.returncode == 1 and "--restart" in text


@pytest.mark.slow
@pytest.mark.data
def test_deployment_superlink_and_supernodes_on_loopback(lego_shards, flower, tmp_path):
    """The same apps with real SuperLink/SuperNode processes (the commands of --deployment)."""
    from dronecap.federated.engines import write_deployment
    from dronecap.federated.state import FedSettings, load_rounds, save_settings

    run = tmp_path / "run"
    save_settings(
        run, FedSettings(shards=lego_shards, cfg=dataclasses.asdict(preset("test")), **SMALL)
    )
    cmds = write_deployment(run, port=18731)
    env = dict(os.environ, FLWR_HOME=cmds[0].split("=", 1)[1])
    env["PATH"] = f"{Path(sys.executable).parent}{os.pathsep}{env['PATH']}"
    for cmd in cmds[1:-1]:  # the SuperLink, then one SuperNode per drone
        flower.start(cmd, env)
        time.sleep(5 if cmd == cmds[1] else 1)
    done = subprocess.run(
        cmds[-1], shell=True, env=env, capture_output=True, text=True, timeout=900
    )
    assert done.returncode == 0, done.stdout + done.stderr
    flower.stop()
    rounds = load_rounds(run)
    assert [r["round"] for r in rounds] == [0, 1, 2]
    assert rounds[-1]["participants"] == 2
    assert (run / "checkpoint.pt").exists()


@pytest.mark.slow
def test_a_round_where_every_drone_fails_is_an_error(tmp_path):
    """`--fail-client all`: round 2 has nothing to average. The command exits 1 with one line
    naming the round, round 2 is not recorded (no global model, no checkpoint), round 1 is."""
    from dronecap.datasets.format import write_dataset
    from dronecap.datasets.shard import shard_dataset
    from tests.reliability.conftest import small_dataset

    write_dataset(tmp_path / "dataset.h5", small_dataset("dataset", 3))
    shard_dataset(tmp_path / "dataset.h5", tmp_path / "shards", 2, "iid")
    args = ["shards", "--clients", "2", "--preset", "test", "--pretrain", "4"]
    args += ["--local-steps", "2", "--rounds", "2", "--eval-views", "1", "--out", "run"]
    res = _federate([*args, "--fail-client", "all", "--fail-round", "2"], cwd=tmp_path)
    out, _ = res.communicate(timeout=800)
    assert res.returncode == 1, out
    last = out.strip().splitlines()[-1]
    assert last.startswith("dronecap federate: error: ") and "round 2: every drone failed" in last
    assert "injected fault: client 1 fails in round 2" in last
    doc = json.loads((tmp_path / "run" / "rounds.json").read_text())
    assert [r["round"] for r in doc["rounds"]] == [0, 1]
    assert not (tmp_path / "run" / "global" / "round_002.pt").exists()
    assert not (tmp_path / "run" / "checkpoint.pt").exists()
