"""Run a benchmark on the committed HEAD, and run dronecap commands from a benchmark.

Long benchmarks run on a snapshot of the last commit (``git archive HEAD`` unpacked under the
benchmark's work folder), not on the shared work tree where edits are in progress: the script is
re-executed with that tree first on ``sys.path``. ``dronecap_command`` then runs the CLI of
whichever tree the script runs on.
"""

from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
# results go to the work tree's benchmarks/results, from a snapshot too (it inherits this by env)
RESULTS = Path(os.environ.get("DRONECAP_RESULTS", REPO / "benchmarks" / "results"))
# the real data next to the repository (a snapshot lives elsewhere: it inherits this by env)
DATA = Path(os.environ.get("DRONECAP_DATA", REPO.parent / "shared" / "data"))
CLI = [sys.executable, "-m", "dronecap.cli"]


def unpack(commit: str, work: Path) -> Path:
    """``work/snapshot-<commit>``: ``git archive`` of ``commit`` (put it on PYTHONPATH: the
    package ``dronecap/`` sits at its root as on disk); unpacked once."""
    git = ["git", "-C", str(REPO)]
    commit = subprocess.run([*git, "rev-parse", "--short", commit], check=True,
                            capture_output=True, text=True).stdout.strip()  # fmt: skip
    root = work / f"snapshot-{commit}"
    if root.exists():
        return root
    tmp = work / f".snapshot-{os.getpid()}"
    tmp.mkdir(parents=True)
    tar = subprocess.run([*git, "archive", commit], check=True, capture_output=True)
    subprocess.run(["tar", "-x", "-C", str(tmp)], input=tar.stdout, check=True)
    try:
        tmp.rename(root)
    except OSError:  # another benchmark unpacked the same commit meanwhile
        subprocess.run(["rm", "-rf", str(tmp)], check=True)
    return root


def rerun_on_snapshot(work: Path, script: Path) -> None:
    """Re-execute ``script`` (with this process's arguments) on a snapshot of HEAD unpacked in
    ``work`` (:func:`unpack`); returns only when already running on a snapshot. Results go to
    the work tree's benchmarks/results (``DRONECAP_RESULTS``)."""
    if os.environ.get("DRONECAP_SNAPSHOT"):
        return
    root = unpack("HEAD", work)
    commit = root.name.removeprefix("snapshot-")
    env = dict(os.environ, DRONECAP_SNAPSHOT=commit, PYTHONPATH=str(root),
               DRONECAP_RESULTS=str(RESULTS), DRONECAP_DATA=str(DATA))  # fmt: skip
    print(f"running on a snapshot of commit {commit}: {root}", flush=True)
    here = root / "benchmarks" / script.name
    os.execve(sys.executable, [sys.executable, str(here), *sys.argv[1:]], env)


def dronecap_command(args: list[str], log: Path, cwd: Path | None = None) -> str:
    """Run ``dronecap ARGS`` single-threaded, its output appended to ``log``; returns stdout.

    The command runs in ``cwd`` (default: the log's folder), never in the repository: ``python
    -m`` puts its working directory first on ``sys.path``, where the work tree's ``dronecap/``
    folder would shadow a snapshot. Raises RuntimeError with the command's last output line
    when it fails."""
    env = dict(os.environ, OMP_NUM_THREADS="1", DRONECAP_PROGRESS="off")
    with open(log, "a") as fh:
        fh.write(f"$ dronecap {' '.join(args)}\n")
        fh.flush()
        t0 = time.perf_counter()
        p = subprocess.run(CLI + args, env=env, capture_output=True, text=True,
                           cwd=cwd or log.parent)  # fmt: skip
        fh.write(p.stdout + p.stderr + f"[exit {p.returncode}, {time.perf_counter() - t0:.0f} s]\n")
    if p.returncode != 0:
        last = (p.stderr.strip() or p.stdout.strip() or "no output").splitlines()[-1]
        raise RuntimeError(f"dronecap {args[0]} failed: {last[:300]}")
    return p.stdout
