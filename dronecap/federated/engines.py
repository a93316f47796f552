"""The two ways to run the federation's Flower apps: the simulation engine on one machine (Ray)
and deployment mode (a SuperLink, one SuperNode per drone, ``flwr run``; docs/federated.md).

Both read everything from the run directory that :func:`dronecap.federated.run.save_settings`
prepared, so an interrupted run resumes where it stopped.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from dronecap.federated.run import clientapp, make_server_app
from dronecap.federated.state import load_rounds, load_settings
from dronecap.files import atomic_output

APP_TOML = """\
[build-system]
requires = ["hatchling"]
build-backend = "hatchling.build"

[project]
name = "dronecap-federate"
version = "1.0.0"
description = "Tiny-DroNeRF FedAvg (the apps live in the installed dronecap package)"
license = "Apache-2.0"
dependencies = []

[tool.flwr.app]
publisher = "dronecap"

[tool.flwr.app.components]
serverapp = "dronecap.federated.run:serverapp"
clientapp = "dronecap.federated.run:clientapp"

[tool.flwr.app.config]
run-dir = ""
"""

FLWR_CONFIG = """\
[superlink]
default = "dronecap"

[superlink.dronecap]
address = "{address}"
{security}
"""


def write_deployment(
    run_dir: Path, host: str = "127.0.0.1", port: int = 8000, keys: Path | None = None
) -> list[str]:
    """Prepare ``run_dir`` for deployment mode; returns the shell commands that run it.

    Writes the Flower app (``RUN/flwr_app/pyproject.toml``, pointing at this module's
    ``serverapp``/``clientapp``) and a Flower config naming the SuperLink
    (``RUN/flwr_home/config.toml``, used through ``FLWR_HOME``). The commands start one
    SuperLink, one SuperNode per drone (``partition-id`` K, runtime port 9094 + K) and
    submit the run with ``flwr run``; each long-running one ends with ``&``.

    ``keys``: a folder from :func:`dronecap.federated.secure.make_keys`: the SuperLink then
    serves TLS only, with its certificate, and admits only SuperNodes whose public key was
    registered (``--enable-supernode-auth``; one ``flwr supernode register`` per drone, over
    TLS); each SuperNode verifies the SuperLink against the CA and signs with its drone key.
    None: plain text and no node authentication (``--insecure``; loopback experiments only).
    """
    from dronecap.federated.secure import CA_CERT, SERVER_CERT, SERVER_KEY, drone_key

    run_dir = Path(run_dir).resolve()
    s = load_settings(run_dir)
    app, home = run_dir / "flwr_app", run_dir / "flwr_home"
    ca = Path(keys).resolve() / CA_CERT if keys else None
    security = f'root-certificates = "{ca}"' if ca else "insecure = true"
    for path, text in (
        (app / "pyproject.toml", APP_TOML),
        (home / "config.toml", FLWR_CONFIG.format(address=f"{host}:{port}", security=security)),
    ):
        path.parent.mkdir(parents=True, exist_ok=True)
        with atomic_output(path) as tmp:
            tmp.write_text(text)
    if keys:
        k_dir = Path(keys).resolve()
        link_sec = (
            f"--ssl-ca-certfile {ca} --ssl-certfile {k_dir / SERVER_CERT} "
            f"--ssl-keyfile {k_dir / SERVER_KEY} --enable-supernode-auth"
        )
        node_sec = [
            f"--root-certificates {ca} --auth-supernode-private-key {drone_key(k_dir, k)[0]}"
            for k in range(s.n_clients)
        ]
    else:
        link_sec, node_sec = "--insecure", ["--insecure"] * s.n_clients
    cmds = [
        f"export FLWR_HOME={home}",
        f"flower-superlink {link_sec} --disable-runtime-dependency-installation "
        f"--host {host} --port {port} &",
    ]
    if keys:
        cmds += [f"flwr supernode register {drone_key(k_dir, k)[1]}" for k in range(s.n_clients)]
    cmds += [
        f"flower-supernode {node_sec[k]} --superlink {host}:{port} --host {host} "
        f"--port {9094 + k} --node-config 'partition-id={k} num-partitions={s.n_clients}' &"
        for k in range(s.n_clients)
    ]
    cmds.append(f"flwr run {app} --run-config \"run-dir='{run_dir}'\" --stream")
    return cmds


@dataclass
class SimulationResources:
    """Ray's footprint: CPUs per drone and for the whole run (no dashboard)."""

    cpus_per_client: float = 1.0
    total_cpus: int = 2
    extra_init_args: dict[str, Any] = field(default_factory=dict)


def run_simulated(run_dir: Path, resources: SimulationResources | None = None) -> list[dict]:
    """Run (or resume) the federation in ``run_dir`` on Flower's simulation engine (Ray).

    ``RUN/federation.json`` must exist (:func:`save_settings`). Returns the rounds recorded.
    """
    from flwr.simulation import run_simulation

    res = resources or SimulationResources()
    s = load_settings(run_dir)
    # Ray starts its workers (the drones) at nice +15 relative to the driver (lower priority);
    # next to any other busy process they then got ~10 % of a core. The driver's instead.
    os.environ.setdefault("RAY_worker_niceness", "0")
    run_simulation(
        server_app=make_server_app(Path(run_dir).resolve()),
        client_app=clientapp,
        num_supernodes=s.n_clients,
        backend_config={
            "client_resources": {"num_cpus": res.cpus_per_client, "num_gpus": 0.0},
            "init_args": {
                "num_cpus": res.total_cpus,
                "include_dashboard": False,
                "log_to_driver": True,
                **res.extra_init_args,
            },
        },
    )
    return load_rounds(run_dir)
