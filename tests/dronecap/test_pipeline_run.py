"""The runner on real stages (lego import -> shard, export): cache hits and misses, dry run,
--force, failures that keep earlier outputs, and resuming an interrupted stage."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from dronecap import cli
from dronecap.pipeline import STAMP, read_stamp

SPEC = """\
t:
  vars: {{scene: {scene}, res: 40}}
  stages:
    import:
      command: import-blender
      params: {{scene_dir: "${{scene}}", resolution: "${{res}}"}}
    shard:
      params: {{input: "${{import}}/dataset.h5", clients: 2, scheme: iid}}
    export:
      command: export-transforms
      params: {{input: "${{import}}/dataset.h5"}}
"""


@pytest.fixture()
def workspace(tmp_path: Path, lego_dir: Path) -> Path:
    (tmp_path / "pipelines.yaml").write_text(SPEC.format(scene=lego_dir))
    return tmp_path


def _mtimes(ws: Path) -> dict[str, float]:
    return {
        s: (ws / "runs/t" / s / STAMP).stat().st_mtime_ns for s in ("import", "shard", "export")
    }


def test_cache_hits_misses_dry_run_and_force(workspace: Path, capsys) -> None:
    assert cli.main(["run", "t", "--workdir", str(workspace)]) == 0
    first = _mtimes(workspace)
    assert (workspace / "runs/t/shard/shards/client_1.h5").exists()
    report = (workspace / "runs/t/report.md").read_text()
    assert "| shard | ran |" in report

    # Nothing changed: every stage is a cache hit, no stamp is rewritten.
    assert cli.main(["run", "t", "--workdir", str(workspace)]) == 0
    assert _mtimes(workspace) == first
    assert "cached" in capsys.readouterr().out

    # A changed parameter of `shard` re-runs that stage only (export does not read it).
    capsys.readouterr()
    assert cli.main(["run", "t", "shard.clients=4", "--dry-run", "--workdir", str(workspace)]) == 0
    out = capsys.readouterr().out
    assert "would run" in out and "parameters changed" in out
    assert _mtimes(workspace) == first  # dry run wrote nothing
    assert cli.main(["run", "t", "shard.clients=4", "--workdir", str(workspace)]) == 0
    after = _mtimes(workspace)
    assert after["shard"] != first["shard"]
    assert after["import"] == first["import"] and after["export"] == first["export"]
    assert (workspace / "runs/t/shard/shards/client_3.h5").exists()

    # A changed upstream parameter re-runs the stage and everything that reads it.
    assert cli.main(["run", "t", "res=20", "shard.clients=4", "--workdir", str(workspace)]) == 0
    again = _mtimes(workspace)
    assert all(again[s] != after[s] for s in again)

    # --force re-runs one stage even though nothing changed.
    assert (
        cli.main(
            [
                "run",
                "t",
                "res=20",
                "shard.clients=4",
                "--force",
                "export",
                "--workdir",
                str(workspace),
            ]
        )
        == 0
    )
    forced = _mtimes(workspace)
    assert forced["export"] != again["export"] and forced["import"] == again["import"]


def test_failing_stage_stops_and_keeps_earlier_outputs(workspace: Path, capsys) -> None:
    code = cli.main(["run", "t", "shard.clients=1000", "--workdir", str(workspace)])
    err = capsys.readouterr().err
    assert code == 1
    assert "dronecap shard: error:" in err and "Traceback" not in err
    assert len([ln for ln in err.splitlines() if "error" in ln]) == 1
    assert read_stamp(workspace / "runs/t/import")["status"] == "done"
    assert read_stamp(workspace / "runs/t/shard")["status"] == "running"
    assert not (workspace / "runs/t/export").exists()  # never started
    assert not (workspace / "runs/t/shard/shards").exists()  # no half-written output

    # Fixed: the import is reused, the rest runs.
    assert cli.main(["run", "t", "--workdir", str(workspace)]) == 0
    assert "cached" in capsys.readouterr().out


def test_interrupted_stage_resumes_in_its_folder(workspace: Path) -> None:
    assert cli.main(["run", "t", "--until", "import", "--workdir", str(workspace)]) == 0
    assert not (workspace / "runs/t/shard").exists()
    assert cli.main(["run", "t", "--workdir", str(workspace)]) == 0
    # Pretend the export stage was killed mid-way: its stamp says "running" with the same key,
    # and it left partial work (a checkpoint, for a trainer) that a resume must not delete.
    stage = workspace / "runs/t/export"
    stamp = json.loads((stage / STAMP).read_text())
    (stage / STAMP).write_text(json.dumps({**stamp, "status": "running"}))
    (stage / "partial.ckpt").write_text("kept")
    assert cli.main(["run", "t", "--workdir", str(workspace)]) == 0
    assert (stage / "partial.ckpt").read_text() == "kept"
    assert read_stamp(stage)["status"] == "done"
    # With another key (a changed parameter) the old partial work is cleared first.
    (stage / STAMP).write_text(json.dumps({**stamp, "status": "running", "key": "other"}))
    assert cli.main(["run", "t", "--workdir", str(workspace)]) == 0
    assert not (stage / "partial.ckpt").exists()


def test_from_requires_earlier_stages_cached(workspace: Path, capsys) -> None:
    assert cli.main(["run", "t", "--from", "shard", "--workdir", str(workspace)]) == 1
    assert "comes before --from" in capsys.readouterr().err


TRAIN_SPEC = """\
t:
  vars: {{scene: {scene}}}
  stages:
    import:
      command: import-blender
      params: {{scene_dir: "${{scene}}", resolution: 24}}
    train:
      params: {{dataset: "${{import}}/dataset.h5", preset: test, steps: 8, threads: 1}}
"""


def test_threads_are_not_in_the_key_and_more_steps_resume(tmp_path: Path, lego_dir: Path) -> None:
    (tmp_path / "pipelines.yaml").write_text(TRAIN_SPEC.format(scene=lego_dir))
    ws = ["--workdir", str(tmp_path)]
    assert cli.main(["run", "t", *ws]) == 0
    train = tmp_path / "runs/t/train"
    assert (train / "checkpoint.pt").exists()  # flat: not runs/t/train/runs/train/
    first = (train / STAMP).stat().st_mtime_ns
    # Another thread count computes the same thing: a cache hit.
    assert cli.main(["run", "t", "train.threads=2", *ws]) == 0
    assert (train / STAMP).stat().st_mtime_ns == first
    # More steps keep the folder (the trainer resumes from its checkpoint, step 8 -> 12).
    (train / "marker").write_text("kept")
    assert cli.main(["run", "t", "train.steps=12", *ws]) == 0
    assert (train / "marker").exists()
    assert json.loads((train / "metrics.json").read_text())["steps"] == 12
    # Any other change starts over in a cleared folder.
    assert cli.main(["run", "t", "train.steps=12", "train.seed=1", *ws]) == 0
    assert not (train / "marker").exists()
