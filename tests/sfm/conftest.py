"""Simulated corridor flights, ingested, shared by the sfm tests that map them."""

from __future__ import annotations

import pytest


def _ingested_corridor(tmp_path_factory, name: str, frames: int):
    """The corridor route of ``simulate --seed 11`` flown as ``frames`` frames, ingested."""
    from dronecap.cli import main as cli

    d = tmp_path_factory.mktemp(name)
    sim = ["-q", "simulate", "--workdir", str(d), "--frames", str(frames), "--seed", "11"]
    assert cli(sim) == 0
    assert cli(["-q", "ingest", "--workdir", str(d), str(d / "flight.mp4")]) == 0
    return d


@pytest.fixture(scope="session")
def corridor(tmp_path_factory):
    """A short simulated corridor flight, ingested (about 50 kept frames)."""
    return _ingested_corridor(tmp_path_factory, "corridor", 100)


@pytest.fixture(scope="session")
def demo_corridor(tmp_path_factory):
    """The demo's 240-frame corridor route, ingested (124 kept frames)."""
    return _ingested_corridor(tmp_path_factory, "demo_corridor", 240)
