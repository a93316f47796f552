"""Run native code that may abort (COLMAP ``CHECK``/``LOG(FATAL)``) in a child process.

A COLMAP fatal error calls ``abort()``: in-process it would kill ``dronecap`` with no message and
no report. :func:`run_isolated` runs a function in a fresh (spawned) Python process, forwards the
events it emits to the caller (progress), returns its result, and turns a crash into
:class:`ChildCrash` naming the last phase reached and the log file. The child's stdout/stderr
(COLMAP's glog chatter) go to that log file.
"""

from __future__ import annotations

import importlib
import json
import os
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from dronecap.errors import InputError

_RESULT = "__result__"
_ERROR = "__error__"


class ChildCrash(InputError):
    """The isolated child died (abort, kill, out of memory) before returning a result."""


def run_isolated(
    target: str,
    kwargs: dict[str, Any],
    on_event: Callable[[list[Any]], None],
    log_file: Path,
) -> Any:
    """Call ``module:function(emit=..., **kwargs)`` in a fresh Python process; return its result.

    Args:
        target: "package.module:function"; the function takes ``emit`` (a callable that sends a
            JSON-able tuple to ``on_event``, where it arrives as a list) and ``kwargs``
            (JSON-able), and returns a JSON-able value.
        on_event: called in this process for every event the child emits, in order.
        log_file: the child's stdout and stderr (native logging) are appended here.

    Raises:
        ChildCrash: the child died without a result (e.g. a native abort).
        InputError: the child raised InputError (its message is kept).
        KeyboardInterrupt: Ctrl-C here; the child is terminated first.
    """
    request = json.dumps({"target": target, "kwargs": kwargs, "log": str(log_file)})
    proc = subprocess.Popen(
        [sys.executable, "-m", "dronecap.sfm.isolate"],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        text=True,
    )
    try:
        proc.stdin.write(request)
        proc.stdin.close()
        for line in proc.stdout:
            kind, payload = json.loads(line)
            if kind == _RESULT:
                return payload
            if kind == _ERROR:
                raise InputError(payload)
            on_event(payload)
    except KeyboardInterrupt:
        proc.terminate()
        raise
    finally:
        proc.stdout.close()
        try:
            proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
    code = proc.returncode
    how = f"signal {-code}" if code < 0 else f"exit code {code}"
    raise ChildCrash(f"the COLMAP process died ({how}); its log is {log_file}")


def _exit_with_parent(parent: int) -> None:
    """Child side: end this process as soon as the parent is gone (killed, crashed)."""
    while os.getppid() == parent:
        time.sleep(0.5)
    os._exit(1)


def _child_main() -> None:
    """Child side: read the request from stdin, send events and the result as JSON lines."""
    request = json.loads(sys.stdin.read())
    channel = os.fdopen(os.dup(1), "w", buffering=1)
    fd = os.open(request["log"], os.O_WRONLY | os.O_CREAT | os.O_APPEND, 0o644)
    os.dup2(fd, 1)
    os.dup2(fd, 2)
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the parent decides what Ctrl-C does
    threading.Thread(target=_exit_with_parent, args=(os.getppid(),), daemon=True).start()

    def send(kind: str, payload: Any) -> None:
        channel.write(json.dumps([kind, payload]) + "\n")

    module, name = request["target"].split(":")
    fn = getattr(importlib.import_module(module), name)
    try:
        send(_RESULT, fn(emit=lambda ev: send("event", list(ev)), **request["kwargs"]))
    except InputError as err:
        send(_ERROR, str(err))


if __name__ == "__main__":
    _child_main()
