"""Federated Tiny-DroNeRF on Flower: the settings, the ClientApp (one per drone), the ServerApp.

The same two apps run under Flower's simulation engine (Ray) and in deployment mode
(``flower-superlink`` + one ``flower-supernode`` per drone, ``flwr run``; both in
:mod:`dronecap.federated.engines`, see docs/federated.md). Everything a process needs is in
the run directory, so a ClientApp may run in a fresh process for every message and an
interrupted run resumes where it stopped:

    RUN/federation.json              settings (shards, config, schedule) -- written by the driver
    RUN/clients/client_K/round_RRR.pt  drone K's trainer after round RRR (weights, grid, Adam)
    RUN/global/round_RRR.pt          global model after round RRR (round 0 = coordinator's pretrain)
    RUN/global/momentum_RRR.npz      server momentum after round RRR (FedAvgM runs only)
    RUN/rounds.json                  per-round PSNR, bytes per direction, link time, failures
    RUN/checkpoint.pt                final global model (``Trainer.load``-able)

Protocol (rounds numbered from 1; round 0 is the pretraining):
 1. ``query``: every drone reports its partition id and train-image count.
 2. ``train.pretrain`` to the coordinator (partition 0): ``pretrain`` steps from scratch; its
    model is the initial global model.
 3. each round, ``train`` to all drones (Flower's FedAvg ``configure_train``): load the global
    model (and the averaged grid with ``exchange_grid``), train ``local_steps``, save the local
    checkpoint, reply with the update; the server averages (``DroneFedAvg``) and tests the
    global model on the common test set.

Non-averaged state stays with the drone across rounds: its occupancy grid (unless exchanged) and
its Adam moments and step counter (never reset: a drone's optimizer continues from its previous
round, only the parameters are replaced by the global ones). A drone that raises or does not
reply within ``round_timeout`` is left out of that round's average; next round it continues
from its last checkpoint. A round where every drone failed raises :class:`FederationFailed`
(never a round recorded with the old model); the rounds before it stay recorded.
"""

from __future__ import annotations

import json
import logging
import re
import time
from pathlib import Path
from typing import Any

import numpy as np
from flwr.app import (
    ArrayRecord,
    ConfigRecord,
    Context,
    Message,
    MessageType,
    MetricRecord,
    RecordDict,
)
from flwr.clientapp import ClientApp
from flwr.serverapp import Grid, ServerApp

from dronecap.datasets.format import open_dataset
from dronecap.federated.downlink import Downlink, broadcast, receive
from dronecap.federated.fedavg import (
    MODEL,
    WEIGHT_KEY,
    DroneFedAvg,
    from_record,
    pack_update,
    payload_bytes,
    to_record,
    unpack_update,
)
from dronecap.federated.hulls import HULL_KEY, hull_record, restrict_to_hulls
from dronecap.federated.state import (
    EVERY_CLIENT,
    FINAL,
    FederationFailed,
    FedSettings,
    client_dir,
    latest_round,
    load_momentum,
    load_rounds,
    load_settings,
    residual_file,
    round_file,
    round_link_times,
    save_momentum,
    save_rounds,
    test_split,
    train_split,
)
from dronecap.files import atomic_output

log = logging.getLogger("dronecap.federate")

PRETRAIN_ACTION = f"{MessageType.TRAIN}.pretrain"


# ----------------------------------------------------------------------------------------------
# ClientApp: one drone
# ----------------------------------------------------------------------------------------------

clientapp = ClientApp()


@clientapp.query()
def _describe(msg: Message, context: Context) -> Message:
    """Reply with this drone's partition id, train-image count and visual hull (hulls.py)."""
    from dronecap.nerf.trainer import Trainer

    k = int(context.node_config["partition-id"])
    s = load_settings(Path(str(msg.content["config"]["run-dir"])))
    train = train_split(s.shards[k])
    info = MetricRecord({"partition-id": k, WEIGHT_KEY: train.n})
    hull = hull_record(Trainer(s.train_config(), train).grid.allowed)
    return Message(RecordDict({"info": info, HULL_KEY: hull}), reply_to=msg)


@clientapp.train("pretrain")
def _pretrain(msg: Message, context: Context) -> Message:
    """The coordinator's pretraining (round 0): train from scratch, reply with the model."""
    return _local_round(msg, context, pretrain=True)


@clientapp.train()
def _train(msg: Message, context: Context) -> Message:
    """One round on this drone: load the global model, train N_l steps, reply with the update."""
    return _local_round(msg, context, pretrain=False)


def _local_round(msg: Message, context: Context, pretrain: bool) -> Message:
    from dronecap.nerf.trainer import Trainer

    config = msg.content["config"]
    run_dir = Path(str(config["run-dir"]))
    s = load_settings(run_dir)
    k = int(context.node_config["partition-id"])
    r = 0 if pretrain else int(config["server-round"])
    if r == s.fail_round and s.fail_client in (k, EVERY_CLIENT):
        raise RuntimeError(f"injected fault: client {k} fails in round {r}")
    train = train_split(s.shards[k])
    folder = client_dir(run_dir, k)
    prev = latest_round(folder, r)
    if prev >= 0:
        trainer = Trainer.load(round_file(folder, prev), train=train)
    else:
        trainer = Trainer(s.train_config(), train)
    received = {} if pretrain else receive(msg.content, folder, r)
    if not pretrain:
        install_global(trainer, received, rebuild=prev < 0)
        if prev < 0:
            trainer.step = s.pretrain  # join the coordinator's learning-rate schedule
    t0 = time.perf_counter()
    trainer.train(s.pretrain if pretrain else s.local_steps)
    train_s = time.perf_counter() - t0
    with atomic_output(round_file(folder, r)) as tmp:
        trainer.save(tmp)
    grid = trainer.grid_state() if s.exchange_grid else None
    if pretrain or not s.quant_bits:
        record = to_record(pack_update(trainer.model_weights(), grid, s.transfer_dtype), s.compress)
    else:
        record = _sparse_record(s, folder, r, prev, trainer, received, grid)
    metrics = MetricRecord({WEIGHT_KEY: train.n, "train-s": train_s, "partition-id": k})
    if not pretrain and str(k) in s.poison:
        record, metrics = _poisoned(s.poison[str(k)], trainer.model_weights(), record, metrics)
    return Message(RecordDict({"arrays": record, "metrics": metrics}), reply_to=msg)


def _sparse_record(
    s: FedSettings,
    folder: Path,
    r: int,
    prev: int,
    trainer: Any,
    received: dict[str, np.ndarray],
    grid: dict[str, np.ndarray] | None,
) -> ArrayRecord:
    """The sparse quantised update of round ``r`` (:func:`sparse.encode_update` against the
    ``received`` global model), the exchanged grid (if any) as whole arrays; the error-feedback
    residual is read from round ``prev``'s file and saved as round ``r``'s."""
    from dronecap.federated.sparse import encode_update

    model, _ = unpack_update(received)
    res_prev = residual_file(folder, prev)
    residual = dict(np.load(res_prev)) if prev >= 0 and res_prev.exists() else {}
    arrays, residual = encode_update(
        trainer.model_weights(), model, residual, s.sparse_rows, s.quant_bits, s.mlp_bits
    )
    with atomic_output(residual_file(folder, r)) as tmp:
        with open(tmp, "wb") as f:
            np.savez(f, **residual)
    record = to_record(pack_update({}, grid, s.transfer_dtype), s.compress)
    for name, arr in arrays.items():
        record[MODEL + name] = arr
    return record


def _poisoned(
    how: str, model: dict[str, np.ndarray], record: ArrayRecord, metrics: MetricRecord
) -> tuple[ArrayRecord, MetricRecord]:
    """Fault injection: a hostile drone's reply. ``how``: "nan" (the model with one NaN),
    "huge" (every weight 1e30, float32) or "count" (the honest update claiming 10^9 images)."""
    if how == "count":
        metrics[WEIGHT_KEY] = 10**9
        return record, metrics
    bad = {k: np.array(v, np.float32) for k, v in model.items()}
    first = sorted(bad)[0]
    if how == "nan":
        bad[first].reshape(-1)[0] = np.nan
    elif how == "huge":
        bad = {k: np.full_like(v, 1e30) for k, v in bad.items()}
    else:
        raise ValueError(f"unknown poison {how!r}: nan, huge or count")
    return to_record(pack_update(bad, None, "fp32")), metrics


def install_global(trainer: Any, update: dict[str, np.ndarray], rebuild: bool) -> None:
    """Load a received global update into ``trainer``.

    The model weights are replaced. An exchanged grid (its densities [R^3]) replaces the local
    one, occupancy re-thresholded as the grid update does (``density > min(thr, mean)``);
    otherwise, with ``rebuild``, the grid is rebuilt from the new model's own densities (a drone
    without a grid of its own, or the server's copy of the global model), else the local grid
    is kept.
    """
    model, grid = unpack_update(update)
    trainer.load_model_weights(model)
    if grid:
        density = np.asarray(grid["density"], np.float32)
        thr = min(trainer.cfg.grid_threshold, float(density.mean()))
        trainer.load_grid_state({"density": density, "occupied": density > thr})
    elif rebuild:
        rebuild_grid(trainer)


REBUILD_PASSES = 16  # full grid updates when a grid is rebuilt from a model alone


def rebuild_grid(trainer: Any, passes: int = REBUILD_PASSES) -> None:
    """Replace ``trainer``'s occupancy grid by one computed from its current model alone.

    ``passes`` warm-up-style updates of every cell from an empty grid, each at one random
    point per cell: a cell ends with about the largest optical thickness seen at ``passes``
    points. One pass is not enough: thin parts whose cell was probed at an empty point
    vanish from the render. On the lego IID benchmark the global model scored 25.38 dB with
    one pass, 26.07 with 4 and 26.14 with 16 (the centralized model: 26.12), on 20 views.
    """
    from dronecap.nerf import occupancy

    # inside the trainer's visual hull (its own train views' silhouettes), as training kept it:
    # outside, the table holds hash collisions of trained cells and untrained values, and a
    # grid that probes them fills the views with floaters (lego, the coordinator after 10000
    # steps, 4 views: 30.41 dB with its own grid, 14.71 rebuilt without the hull)
    grid = occupancy.restrict(
        occupancy.init_state(trainer.grid_cfg, trainer.device), trainer.grid.allowed
    )
    for _ in range(passes):
        grid = trainer.updated_grid(grid, 0)
    trainer.grid = grid


# ----------------------------------------------------------------------------------------------
# ServerApp: the coordinator's aggregation and the per-round test
# ----------------------------------------------------------------------------------------------


def make_server_app(run_dir: str | Path | None = None) -> ServerApp:
    """The ServerApp of a run; ``run_dir`` None: taken from the run config key ``run-dir``."""
    app = ServerApp()

    @app.main()
    def _main(grid: Grid, context: Context) -> None:
        serve(grid, Path(run_dir or str(context.run_config["run-dir"])))

    return app


serverapp = make_server_app()  # deployment: `flwr run` passes run-dir in the run config


def serve(grid: Grid, run_dir: Path) -> None:
    """Run (or resume) the federation whose settings are in ``run_dir``; see the module doc."""
    s = load_settings(run_dir)
    history = load_rounds(run_dir)
    evaluator = GlobalEvaluator(s)
    nodes, hulls = _discover(grid, s, run_dir)
    restrict_to_hulls(evaluator.trainer, hulls)  # the global grid inside every drone's hull
    if not history:
        t0 = time.perf_counter()
        msg = _message(grid, nodes[0], PRETRAIN_ACTION, ConfigRecord({"run-dir": str(run_dir)}))
        (reply,) = list(grid.send_and_receive([msg], timeout=s.round_timeout))
        if reply.has_error():
            reason = _last_line(reply.error.reason)
            raise FederationFailed(f"the coordinator's pretraining failed: {reason}", run_dir)
        update = from_record(reply.content["arrays"])
        entry = {"round": 0, "bytes_up": {"0": payload_bytes(reply.content)}, "bytes_down": {}}
        history.append(evaluator.finish_round(run_dir, 0, update, entry, t0))
        save_rounds(run_dir, s, history)
    last = history[-1]["round"]
    current = pack_update(*evaluator.load_global(run_dir, last), "fp32")
    downlink = Downlink.for_run(s, history, current)
    strategy = DroneFedAvg(
        min_train_nodes=s.n_clients,
        min_available_nodes=s.n_clients,
        arrayrecord_key="arrays",
        server_learning_rate=s.server_lr,
        server_momentum=s.server_momentum,
        visibility=s.visibility,
        downlink=downlink,
        table_step=s.table_step,
    )
    strategy.known_examples = {
        node: len(open_dataset(s.shards[k]).indices("train")) for k, node in nodes.items()
    }
    part = {node: k for k, node in nodes.items()}
    strategy.resume(current, load_momentum(run_dir, last))
    arrays = broadcast(s, current, downlink)
    for r in range(last + 1, s.rounds + 1):
        t0 = time.perf_counter()
        config = ConfigRecord({"run-dir": str(run_dir)})
        messages = strategy.configure_train(r, arrays, config, grid)
        replies = list(grid.send_and_receive(messages, timeout=s.round_timeout))
        agg, _ = strategy.aggregate_train(r, replies)
        st = strategy.last_round
        failed = {str(part[n]): _last_line(reason) for n, reason in st["failed"].items()}
        for n in set(st["bytes_down"]) - set(st["bytes_up"]) - set(st["failed"]):
            failed[str(part[n])] = f"no reply within {s.round_timeout:.0f} s"
        for k, reason in sorted(failed.items()):
            log.warning("round %d: client %s left out of the average: %s", r, k, reason)
        if agg is None or not st["bytes_up"]:
            reasons = "; ".join(f"{k}: {why}" for k, why in sorted(failed.items()))
            raise FederationFailed(
                f"round {r}: every drone failed, nothing to average ({reasons}); rounds up to "
                f"{history[-1]['round']} are kept, a rerun resumes there",
                run_dir,
            )
        entry = {
            "round": r,
            "bytes_down": {str(part[n]): b for n, b in st["bytes_down"].items()},
            "bytes_up": {str(part[n]): b for n, b in st["bytes_up"].items()},
            "failed": failed,
        }
        update = from_record(agg)
        history.append(evaluator.finish_round(run_dir, r, update, entry, t0))
        save_momentum(run_dir, r, strategy.server_state())
        save_rounds(run_dir, s, history)
        arrays = broadcast(s, update, downlink)
    evaluator.write_final(run_dir, history[-1]["round"])


def _last_line(reason: str) -> str:
    """The last non-empty line of an error report, without terminal colour codes."""
    lines = [ln.strip() for ln in re.sub(r"\x1b\[[0-9;]*m", "", reason).splitlines()]
    return ([ln for ln in lines if ln] or [""])[-1][:300]


def _message(grid: Grid, node: int, message_type: str, config: ConfigRecord) -> Message:
    return Message(RecordDict({"config": config}), dst_node_id=node, message_type=message_type)


def _discover(
    grid: Grid, s: FedSettings, run_dir: Path
) -> tuple[dict[int, int], dict[int, ArrayRecord]]:
    """partition id -> node id of every drone (waits until all ``n_clients`` are connected),
    and partition id -> the hull record it sent."""
    while len(node_ids := list(grid.get_node_ids())) < s.n_clients:
        time.sleep(1.0)
    config = ConfigRecord({"run-dir": str(run_dir)})
    msgs = [_message(grid, n, MessageType.QUERY, config) for n in node_ids]
    found: dict[int, int] = {}
    hulls: dict[int, ArrayRecord] = {}
    for reply in grid.send_and_receive(msgs, timeout=s.round_timeout):
        if reply.has_error():
            why = _last_line(reply.error.reason)
            raise FederationFailed(f"drone {reply.metadata.src_node_id} failed to start: {why}")
        k = int(reply.content["info"]["partition-id"])
        found[k] = reply.metadata.src_node_id
        if HULL_KEY in reply.content:
            hulls[k] = reply.content[HULL_KEY]
    if sorted(found) != list(range(s.n_clients)):
        raise FederationFailed(f"expected partitions 0..{s.n_clients - 1}, found {sorted(found)}")
    return found, hulls


class GlobalEvaluator:
    """Holds a trainer for the global model: tests it, checkpoints it, writes the final one."""

    def __init__(self, s: FedSettings) -> None:
        from dronecap.nerf.trainer import Trainer

        self.s = s
        self.test = test_split(s.shards[0], s.eval_views)
        self.trainer = Trainer(s.train_config(), train_split(s.shards[0]))

    def finish_round(
        self, run_dir: Path, r: int, update: dict[str, np.ndarray], entry: dict, t0: float
    ) -> dict:
        """Install ``update`` as the global model, save it, test it; returns the round's entry.

        Without an exchanged grid the global model's grid is rebuilt from its own densities.
        """
        install_global(self.trainer, update, rebuild=True)
        with atomic_output(round_file(Path(run_dir) / "global", r)) as tmp:
            self.trainer.save(tmp)
        metrics = self.trainer.evaluate(self.test)
        if not (np.isfinite(metrics["psnr"]) and np.isfinite(metrics["ssim"])):
            raise FederationFailed(
                f"round {r}: the global model's test PSNR is {metrics['psnr']} (diverged); "
                "nothing recorded for this round",
                run_dir,
            )
        up = sum(entry["bytes_up"].values())
        down = sum(entry["bytes_down"].values())
        entry.update(
            psnr=float(metrics["psnr"]),
            ssim=float(metrics["ssim"]),
            steps=self.s.pretrain + r * self.s.local_steps,
            participants=len(set(entry["bytes_up"]) - set(entry.get("failed", {}))),
            bytes_up_total=up,
            bytes_down_total=down,
            **round_link_times(entry),
            wall_s=time.perf_counter() - t0,
        )
        entry.setdefault("failed", {})
        log.info(
            "round %d: global PSNR %.2f dB (%d clients)", r, entry["psnr"], entry["participants"]
        )
        return entry

    def load_global(self, run_dir: Path, r: int) -> tuple[dict, dict | None]:
        """(model, grid or None) of the saved global model of round ``r``, for broadcasting."""
        from dronecap.nerf.trainer import Trainer

        t = Trainer.load(round_file(Path(run_dir) / "global", r))
        return t.model_weights(), (t.grid_state() if self.s.exchange_grid else None)

    def write_final(self, run_dir: Path, r: int) -> None:
        """Make ``run_dir`` a run folder of ``dronecap render``/``eval``: ``checkpoint.pt`` (the
        global model of round ``r``) and ``run.json`` (the coordinator's shard, which holds the
        common test set)."""
        src = round_file(Path(run_dir) / "global", r)
        with atomic_output(Path(run_dir) / FINAL) as tmp:
            tmp.write_bytes(src.read_bytes())
        info = {"dataset": self.s.shards[0], "config": self.trainer.cfg.__dict__, "round": r}
        with atomic_output(Path(run_dir) / "run.json") as tmp:
            tmp.write_text(json.dumps(info, indent=1, default=list))
