"""The federated tests reuse the trainer tests' analytic cube scene; Messages need a task."""

import pytest
from flwr.supercore.task_identity import TaskIdentity

from tests.nerf.conftest import cube_rgb, make_cube  # noqa: F401  (pytest fixtures)


@pytest.fixture
def server_task(monkeypatch):
    """The identity Flower gives a ServerApp's process (run 1, node 0, task 1): Messages need
    it."""
    monkeypatch.setattr(TaskIdentity, "_run_id", 1)
    monkeypatch.setattr(TaskIdentity, "_node_id", 0)
    monkeypatch.setattr(TaskIdentity, "_task_id", 1)
