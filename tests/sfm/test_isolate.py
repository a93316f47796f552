"""A native abort in the isolated child becomes an InputError here, not a dead process."""

from __future__ import annotations

import pytest

from dronecap.errors import InputError
from dronecap.sfm.isolate import ChildCrash, run_isolated

CHILD = """
import os


def work(emit, n):
    for i in range(n):
        emit(("step", i))
    return {"sum": n * (n - 1) // 2}


def abort(emit):
    emit(("phase", "about to abort"))
    os.abort()  # what a COLMAP CHECK failure does


def refuse(emit):
    from dronecap.errors import InputError

    raise InputError("bad frames")
"""


@pytest.fixture
def child_module(tmp_path, monkeypatch):
    (tmp_path / "isolate_child.py").write_text(CHILD)
    monkeypatch.setenv("PYTHONPATH", str(tmp_path))
    return tmp_path


def test_result_and_events_come_back(child_module):
    events = []
    out = run_isolated("isolate_child:work", {"n": 4}, events.append, child_module / "log")
    assert out == {"sum": 6}  # 0 + 1 + 2 + 3
    assert events == [["step", 0], ["step", 1], ["step", 2], ["step", 3]]


def test_native_abort_is_reported_not_fatal(child_module):
    events = []
    with pytest.raises(ChildCrash, match="signal 6"):
        run_isolated("isolate_child:abort", {}, events.append, child_module / "log")
    assert events == [["phase", "about to abort"]]


def test_input_error_keeps_its_message(child_module):
    with pytest.raises(InputError, match="bad frames"):
        run_isolated("isolate_child:refuse", {}, lambda e: None, child_module / "log")
