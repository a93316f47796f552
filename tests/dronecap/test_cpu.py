"""Thread count of the torch commands: the cores not already busy."""

from __future__ import annotations

import pytest

from dronecap import cpu


@pytest.mark.parametrize(
    ("cores", "load", "expected"),
    [(2, 0.0, 2), (2, 0.4, 2), (2, 1.0, 1), (2, 8.0, 1), (8, 2.2, 6), (8, 0.0, 8)],
)
def test_idle_cores_subtracts_the_load(monkeypatch, cores, load, expected):
    monkeypatch.setattr(cpu.os, "cpu_count", lambda: cores)
    monkeypatch.setattr(cpu.os, "getloadavg", lambda: (load, load, load))
    assert cpu.idle_cores() == expected


def test_requested_threads_win_and_are_set(monkeypatch):
    import torch

    before = torch.get_num_threads()
    monkeypatch.setattr(cpu.os, "getloadavg", lambda: (100.0, 100.0, 100.0))
    try:
        assert cpu.use_torch_threads(None) == 1 == torch.get_num_threads()
        assert cpu.use_torch_threads(3) == 3 == torch.get_num_threads()
    finally:
        torch.set_num_threads(before)
