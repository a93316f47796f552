"""``dronecap federate``: FedAvg of Tiny-DroNeRF across drones on Flower (simulation engine)."""

from __future__ import annotations

import json
import shutil
from dataclasses import dataclass
from pathlib import Path

from dronecap.settings import Settings as Base
from dronecap.settings import setting


def _client_or_all(text: str) -> int:
    """``--fail-client``: a drone number, or ``all`` (every drone)."""
    return -2 if text == "all" else int(text)  # -2: federated.state.EVERY_CLIENT


@dataclass(kw_only=True)
class Settings(Base):
    """Options of ``dronecap federate``."""

    input: str | None = setting(
        None,
        positional=True,
        help="dataset.h5 (sharded here into RUN/shards) or a shards/ folder of client_K.h5 "
        "(default: the workspace's shards/)",
    )
    clients: int = setting(4, minimum=1, help="drones K (default 4)")
    scheme: str = setting("iid", choices=("iid", "sector"), help="sharding scheme")
    # The default schedule: many short rounds, 1000 + 70 x 200 (15000 steps on the critical
    # path, as 10000 + 5 x 1000 before). Lego, 4 drones, 40 views (docs/federated.md session
    # 16): sector 29.68 dB (was 26.83), central 30.98: short rounds keep the drones' models
    # close while the learning rate is high. IID at this schedule: 31.76 with an error feedback
    # since removed (`carry`; was 29.37); with the default `add` stopped after 45 rounds.
    pretrain: int = setting(
        1000, minimum=0, help="coordinator's N_pt steps (default 1000: many short rounds)"
    )
    local_steps: int = setting(
        200,
        minimum=1,
        help="N_l steps per drone per round (default 200: with 70 rounds, lego 4 drones, sector "
        "29.68 dB against 26.83 for 10000 + 5 x 1000 and central 30.98; docs/federated.md "
        "session 16)",
    )
    rounds: int = setting(70, minimum=1, help="communication rounds R (default 70)")
    preset: str = setting(
        "scene-sized", help="trainer preset (nerf/config.py; default: sized to the scene, once)"
    )
    exchange_grid: bool = setting(False, help="also average the occupancy grids")
    transfer_dtype: str = setting(
        "fp16", choices=("fp32", "fp16"), help="dtype of whole arrays sent (default fp16)"
    )
    quant_bits: int = setting(
        4,
        choices=(0, 4, 8),
        help="drones send their change quantised to this many bits (hash table; MLPs: "
        "--mlp-bits), with error feedback; 0: whole arrays in --transfer-dtype (default 4)",
    )
    mlp_bits: int = setting(
        4,
        choices=(4, 8),
        help="with --quant-bits: bits of the MLPs' change (default 4: the bytes go to more "
        "table rows, +0.31 dB on lego sector, docs/federated.md session 13)",
    )
    sparse_rows: float = setting(
        0.04,
        minimum=1e-4,
        maximum=1.0,
        help="with --quant-bits: fraction of hash-table rows a drone sends, the most changed "
        "(default 0.04)",
    )
    down_rows: float = setting(
        0.0,
        minimum=0.0,
        maximum=1.0,
        help="with --quant-bits: the server broadcasts the global model's change, this fraction "
        "of hash-table rows (the most changed), each drone keeping its copy, e.g. 0.05; 0: the "
        "whole model every round (default: not yet measured better over 10 rounds)",
    )
    compress: bool = setting(
        False,
        help="with --quant-bits 0: send every array losslessly compressed (byte shuffle + "
        "deflate; ~14%% smaller fp16 updates)",
    )
    plain_average: bool = setting(
        False,
        help="average every hash-table row over all drones (plain FedAvg); default: each row "
        "over the drones that sent it (visibility-weighted)",
    )
    server_lr: float = setting(
        2.0,
        minimum=1e-6,
        help="FedAvgM server step size on the averaged update (default 2; 1 with momentum 0: "
        "plain FedAvg)",
    )
    server_momentum: float = setting(
        0.5, minimum=0.0, maximum=0.999, help="FedAvgM server momentum (default 0.5)"
    )
    table_step: str = setting(
        "mean",
        choices=("server", "mean"),
        help="hash table: the drones' mean change itself (rows one drone saw are that drone's "
        "change), or the FedAvgM server step as the MLPs (default mean: +0.86 dB on a swarm's "
        "drone shards, benchmarks/results/federated_swarm.md)",
    )
    baselines: bool = setting(
        False, help="also train centralized and single-drone baselines on the same step budget"
    )
    eval_views: int = setting(
        20,
        minimum=0,
        help="test views per round, evenly spaced (0: all; default 20: 70 rounds on lego's 200 "
        "test views would render ~1 h on a CPU core, more than the training)",
    )
    round_timeout: float = setting(3600.0, minimum=1.0, help="seconds per round (>= 1)")
    seed: int = setting(0, minimum=0, help="random seed")
    fail_client: int = setting(
        -1,
        minimum=-2,
        parse=_client_or_all,
        help="fault injection: this drone raises in --fail-round (left out of that average); "
        "'all': every drone does (the run stops with an error)",
    )
    fail_round: int = setting(-1, minimum=-1, help="the round --fail-client fails in")
    deployment: bool = setting(
        False,
        help="do not simulate: prepare --out for deployment mode (a SuperLink and one SuperNode "
        "per drone) and print the commands that run it",
    )
    superlink_host: str = setting(
        "127.0.0.1", help="with --deployment: the SuperLink's address (in its TLS certificate)"
    )
    superlink_port: int = setting(8000, minimum=1, maximum=65535, help="with --deployment")
    keys: str | None = setting(
        None,
        help="with --deployment: folder of TLS certificates and drone keys (made there when it "
        "holds none; default RUN/keys)",
    )
    insecure: bool = setting(
        False,
        help="with --deployment: plain text and no node authentication (loopback tests only)",
    )
    restart: bool = setting(False, help="discard an existing run in --out")
    out: str | None = setting(None, help="run folder (default: runs/federate in the workspace)")


def run(args: Settings) -> int:
    """Shard if needed, run (or resume) the federation, the baselines, and the plot."""
    import dataclasses

    from dronecap import workspace
    from dronecap.errors import InputError
    from dronecap.files import sha256_file
    from dronecap.nerf.config import preset

    out = workspace.resolve(args.workdir, args.out, workspace.FEDERATE_RUN).resolve()
    src = workspace.resolve(args.workdir, args.input, workspace.SHARDS)
    if not src.exists():
        raise InputError("no such dataset or shards folder", src)
    try:
        cfg = preset(args.preset)
    except KeyError as err:
        raise InputError(str(err.args[0])) from None
    if args.restart and out.exists():
        shutil.rmtree(out)
    out.mkdir(parents=True, exist_ok=True)
    shards = _shards(src, out, args)

    from dronecap.federated import engines
    from dronecap.federated import state as fed
    from dronecap.federated.sizing import resolve_once
    from dronecap.nerf.resolve import choice_lines

    resolved = resolve_once(cfg, shards)
    print("\n".join(choice_lines(resolved, cfg.sized)))
    cfg = resolved.config

    same_name = {f.name for f in dataclasses.fields(fed.FedSettings)} & set(vars(args))
    s = fed.FedSettings(
        shards=[str(p) for p in shards],
        cfg=dataclasses.asdict(cfg),
        shard_sha256=[sha256_file(p) for p in shards],
        **{name: getattr(args, name) for name in same_name},  # the run's options, by name
        visibility=not args.plain_average,
    )
    if (out / fed.SETTINGS).exists() and (old := fed.load_settings(out)) != s:
        what = "settings"
        if not old.shard_sha256 and dataclasses.replace(old, shard_sha256=s.shard_sha256) == s:
            what = "no record of its shards' contents (made by an older dronecap)"
        elif dataclasses.replace(old, shard_sha256=s.shard_sha256) == s:
            pairs = zip(shards, old.shard_sha256, s.shard_sha256, strict=True)
            what = f"other shard contents ({', '.join(p.name for p, a, b in pairs if a != b)})"
        raise InputError(
            f"holds a run with {what}: pass --restart to discard it, or another --out", out
        )
    fed.save_settings(out, s)
    if args.deployment:
        cmds = engines.write_deployment(
            out,
            args.superlink_host,
            args.superlink_port,
            None if args.insecure else _keys(out, args),
        )
        print("deployment mode: run these (then this command again, for --baselines and the plot):")
        print("\n".join(cmds))
        return 0
    rounds = fed.load_rounds(out)
    if rounds and rounds[-1]["round"] < s.rounds:
        print(f"resuming after round {rounds[-1]['round']} of {s.rounds}")
    if not rounds or rounds[-1]["round"] < s.rounds:
        rounds = engines.run_simulated(out)
    if not rounds or rounds[-1]["round"] != s.rounds:
        raise InputError(f"the federation stopped after {len(rounds)} rounds; see the log", out)
    if args.baselines:
        from dronecap.federated.baselines import merge_curves, run_baselines

        run_baselines(out, s)
        merge_curves(out, s)
    from dronecap.federated.plot import plot_runs

    doc = json.loads((out / fed.ROUNDS).read_text())
    png = plot_runs({f"{args.scheme} ({s.n_clients} drones)": doc}, out / "psnr.png")
    _summary(doc)
    print(f"wrote {out}: rounds.json, {'psnr.png, ' if png else ''}checkpoint.pt")
    return 0


def _keys(out: Path, args: Settings) -> Path:
    """The deployment's key folder: ``--keys`` or RUN/keys, with a new CA, SuperLink
    certificate and one key pair per drone made there when it holds no CA yet."""
    from dronecap.federated.secure import CA_CERT, make_keys

    keys = Path(args.keys).resolve() if args.keys else out / "keys"
    if not (keys / CA_CERT).exists():
        make_keys(keys, args.clients, [args.superlink_host])
        print(f"made TLS certificates and {args.clients} drone key pairs in {keys}")
    return keys


def _shards(src: Path, out: Path, args: Settings) -> list[Path]:
    """The drones' shard files: those of a shards/ folder, or new ones cut from a dataset."""
    from dronecap.errors import InputError

    if src.is_file():
        from dronecap.datasets.shard import shard_dataset

        folder = out / "shards"
        if not (folder / "client_0.h5").exists():
            shard_dataset(src, folder, args.clients, args.scheme, seed=args.seed)
        src = folder
    files = sorted(src.glob("client_*.h5"), key=lambda p: int(p.stem.split("_")[1]))
    if not files:
        raise InputError("holds no client_K.h5 shard files (run `dronecap shard`)", src)
    if [int(p.stem.split("_")[1]) for p in files] != list(range(len(files))):
        raise InputError("shard files must be client_0.h5 ... client_{K-1}.h5", src)
    if len(files) != args.clients:
        raise InputError(f"holds {len(files)} shards but --clients is {args.clients}", src)
    _check_shards(files)
    return [p.resolve() for p in files]


def _check_shards(files: list[Path]) -> None:
    """Read every shard before the drones start: a damaged one is one line naming it; each must
    hold train views, and the coordinator's (client_0) the common test views."""
    from dronecap.datasets.format import open_dataset
    from dronecap.errors import InputError

    for k, path in enumerate(files):
        ds = open_dataset(path, kinds=("shard", "dataset"))
        if ds.poses is None or (ds.intrinsics is None and ds.cameras is None):
            raise InputError("has no camera poses or intrinsics to train on", path)
        if not len(ds.indices("train")):
            raise InputError("holds no train views", path)
        if k == 0 and not len(ds.indices("test")):
            raise InputError("holds no test views to score the global model on", path)


def _summary(doc: dict) -> None:
    """Print one line per round and the baselines' final PSNR."""
    for r in doc["rounds"]:
        up = r["bytes_up_total"] / 1e6
        link = "" if r.get("link_s") is None else f", link {r['link_s']:.2f} s"
        fails = f", left out: {sorted(r['failed'])}" if r.get("failed") else ""
        print(f"round {r['round']:3d}: PSNR {r['psnr']:6.2f} dB, up {up:.3f} MB{link}{fails}")
    for name, curve in sorted(doc.get("baselines", {}).items()):
        print(f"{name:>12}: PSNR {curve[-1]['psnr']:6.2f} dB after {curve[-1]['steps']} steps")
