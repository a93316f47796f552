"""Error feedback ``carry`` in a real Flower run: a drone trains from the model it received plus
its residual (its unsent change), and what it sends plus its new residual is the whole change
from the received model, the old residual included once."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from dronecap.federated.downlink import replica_file
from dronecap.federated.sparse import decode_delta, encode_update


def _npz(path) -> dict[str, np.ndarray]:
    with np.load(path) as z:
        return {k: z[k] for k in z.files}


@pytest.mark.data
def test_carry_trains_from_received_plus_residual_and_sends_each_change_once(lego_run):
    """2 lego drones, 2 rounds of 4 steps, then a round of 0 steps, so what a drone trained
    from is its saved model: it must be the received model (its replica, sparse downloads)
    plus the residual of round 2. That round's change from the received model is then exactly
    the old residual: what the drone sends (its update, re-encoded: the codec is
    deterministic) plus its new residual must add up to it, not to twice it (the residual
    added to the change again, as ``add`` does)."""
    from dronecap.federated.engines import run_simulated
    from dronecap.federated.state import load_settings, residual_file, round_file, save_settings
    from dronecap.nerf.trainer import Trainer

    run = lego_run(
        2,
        rounds=2,
        quant_bits=4,
        sparse_rows=0.05,
        down_rows=0.05,
        visibility=True,
        feedback="carry",
    )
    run_simulated(run)
    s = load_settings(run)
    save_settings(run, dataclasses.replace(s, rounds=3, local_steps=0))
    *_, r3 = run_simulated(run)
    assert r3["round"] == 3 and r3["participants"] == 2
    for k in (0, 1):
        folder = run / "clients" / f"client_{k}"
        received = _npz(replica_file(folder, 2))  # the model drone k received for round 3
        residual = _npz(residual_file(folder, 2))
        assert sum(float(np.abs(v).sum()) for v in residual.values()) > 0  # something unsent
        local = Trainer.load(round_file(folder, 3)).model_weights()
        for name, v in received.items():  # what it trained from (0 steps): received + residual
            np.testing.assert_allclose(local[name], v + residual[name], rtol=0, atol=1e-6)
        arrays, _ = encode_update(local, received, {}, s.sparse_rows, s.quant_bits, s.mlp_bits)
        new = _npz(residual_file(folder, 3))
        for name in received:
            sent = decode_delta(arrays[name])[0]
            np.testing.assert_allclose(sent + new[name], residual[name], rtol=0, atol=1e-5)
