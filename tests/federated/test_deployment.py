"""A secure deployment on loopback: SuperLink with TLS and node authentication, 4 SuperNodes.

Slow (real Flower processes, a few minutes): a SuperNode whose key is not registered is
refused, a plain-text connection is refused, and a drone sending NaN and one sending a
1e30 model are left out of the round with their reasons while the run completes."""

from __future__ import annotations

import os
import subprocess
import sys
import time
import urllib.request
from pathlib import Path

import numpy as np
import pytest

PORT = 18743


@pytest.mark.slow
@pytest.mark.data
def test_tls_and_node_auth_refuse_strangers_and_poisoned_updates(lego_run, flower, tmp_path):
    from dronecap.federated.engines import write_deployment
    from dronecap.federated.secure import drone_key, make_keys
    from dronecap.federated.state import load_rounds

    run = lego_run(4, rounds=1, quant_bits=8, sparse_rows=0.1, poison={"2": "nan", "3": "huge"})
    keys, strangers = tmp_path / "keys", tmp_path / "strangers"
    make_keys(keys, 4)
    make_keys(strangers, 1)
    cmds = write_deployment(run, port=PORT, keys=keys)
    assert "--insecure" not in " ".join(cmds)
    env = dict(os.environ, FLWR_HOME=cmds[0].split("=", 1)[1])
    env["PATH"] = f"{Path(sys.executable).parent}{os.pathsep}{env['PATH']}"
    register = [c for c in cmds if c.startswith("flwr supernode register")]
    nodes = [c for c in cmds if c.startswith("flower-supernode")]
    flower.start(cmds[1], env, tmp_path / "superlink.log")
    time.sleep(8)
    for cmd in register:  # the four drones' public keys, over TLS
        done = subprocess.run(cmd, shell=True, env=env, capture_output=True, text=True)
        assert done.returncode == 0, done.stdout + done.stderr
    # plain text to the TLS port: no HTTP answer
    with pytest.raises(OSError):
        urllib.request.urlopen(f"http://127.0.0.1:{PORT}/", timeout=10)
    # a stranger with a valid TLS trust but an unregistered key, as partition 9: if it
    # were admitted the server would find partitions 0..3 and 9 and stop with an error
    stranger = nodes[0].replace(str(drone_key(keys, 0)[0]), str(drone_key(strangers, 0)[0]))
    stranger = stranger.replace("partition-id=0", "partition-id=9").replace("9094", "9099")
    flower.start(stranger, env, tmp_path / "stranger.log")
    insecure = nodes[1].split(" --root-certificates")[0] + " --insecure --superlink"
    insecure += f" 127.0.0.1:{PORT} --port 9098 --node-config 'partition-id=8'"
    flower.start(insecure, env, tmp_path / "plain.log")
    for k, cmd in enumerate(nodes):
        flower.start(cmd, env, tmp_path / f"node_{k}.log")
    time.sleep(2)
    done = subprocess.run(
        cmds[-1], shell=True, env=env, capture_output=True, text=True, timeout=1500
    )
    assert done.returncode == 0, done.stdout + done.stderr
    flower.stop()
    r0, r1 = load_rounds(run)
    assert sorted(r1["bytes_up"]) == ["0", "1", "2", "3"]  # only the four listed drones
    assert sorted(r1["failed"]) == ["2", "3"] and r1["participants"] == 2
    assert "non-finite" in r1["failed"]["2"] and "magnitude 1e+30" in r1["failed"]["3"]
    assert np.isfinite(r1["psnr"]) and (run / "checkpoint.pt").exists()
    logs = {n: (tmp_path / f"{n}.log").read_text() for n in ("stranger", "plain", "superlink")}
    assert "Failed to activate SuperNode" in logs["stranger"]  # refused, and it stopped
    assert "Attempted to register SuperNode with public key" in logs["superlink"]  # logged
    assert "Connection attempt failed" in logs["plain"]


def test_keys_are_a_ca_a_server_certificate_and_drone_key_pairs(tmp_path):
    from cryptography import x509
    from cryptography.hazmat.primitives import serialization

    from dronecap.federated.engines import write_deployment
    from dronecap.federated.secure import drone_key, make_keys
    from dronecap.federated.state import FedSettings, save_settings

    make_keys(tmp_path / "keys", 2, ["10.0.0.7"])
    ca = x509.load_pem_x509_certificate((tmp_path / "keys" / "ca.crt").read_bytes())
    server = x509.load_pem_x509_certificate((tmp_path / "keys" / "server.crt").read_bytes())
    server.verify_directly_issued_by(ca)
    alt = server.extensions.get_extension_for_class(x509.SubjectAlternativeName).value
    assert "10.0.0.7" in {str(ip) for ip in alt.get_values_for_type(x509.IPAddress)}
    for k in range(2):
        private, public = drone_key(tmp_path / "keys", k)
        assert private.stat().st_mode & 0o077 == 0  # private keys: owner only
        key = serialization.load_ssh_private_key(private.read_bytes(), None)
        pub = serialization.load_ssh_public_key(public.read_bytes())
        assert key.public_key().public_numbers() == pub.public_numbers()
    run = tmp_path / "run"
    save_settings(
        run, FedSettings(shards=["a.h5", "b.h5"], cfg={}, pretrain=1, local_steps=1, rounds=1)
    )
    cmds = write_deployment(run, keys=tmp_path / "keys")
    text = "\n".join(cmds)
    assert "--insecure" not in text and "--enable-supernode-auth" in text
    assert (
        text.count("flwr supernode register") == 2
        and text.count("--auth-supernode-private-key") == 2
    )
    assert 'root-certificates = "' in (run / "flwr_home" / "config.toml").read_text()
