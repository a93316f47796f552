"""``dronecap sfm`` on a swarm, on real files: two simulated drones with their own cameras posed
in one model (a camera per drone in posed.h5, per-drone report records, accuracy against the
swarm's ground truth); two unrelated flights given together stay apart (slow)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from dronecap.cli import main
from dronecap.datasets.format import open_dataset

FRAMES = 60  # per drone: 2 s of flight at 30 Hz


@pytest.fixture(scope="module")
def swarm_run(tmp_path_factory) -> Path:
    """simulate --drones 2 (clean sensor) -> ingest -> sfm --gt swarm.json, in one workspace."""
    work = tmp_path_factory.mktemp("swarm_sfm")
    w = ["--workdir", str(work)]
    swarm = ["--drones", "2", "--frames", str(FRAMES), "--seed", "3"]
    assert main(["-q", "simulate", *w, *swarm]) == 0
    assert main(["-q", "ingest", *w, str(work / "swarm")]) == 0
    gt = str(work / "swarm" / "swarm.json")
    assert main(["-q", "sfm", *w, "--gt", gt, "--quiet"]) == 0
    return work


def test_two_drones_are_posed_in_one_model_with_their_own_cameras(swarm_run: Path) -> None:
    frames = open_dataset(swarm_run / "frames.h5")
    posed = open_dataset(swarm_run / "posed.h5")
    report = json.loads((swarm_run / "sfm" / "report.json").read_text())
    assert report["status"] == "ok" and report["flights"]["main"] == [0, 1]
    # both drones' frames in one model, each with its own (known, fixed) camera
    assert set(posed.drones().tolist()) == {0, 1} and len(posed.cameras) == 2
    for d in (0, 1):
        known = frames.camera_of(int(np.flatnonzero(frames.drones() == d)[0]))
        assert posed.camera_of(int(np.flatnonzero(posed.drones() == d)[0])) == known
    assert posed.cameras[0] != posed.cameras[1]
    records = report["drones"]
    assert [r["name"] for r in records] == ["drone_0", "drone_1"]
    for r in records:
        assert r["linked"] and r["registered"] >= 0.9 * r["frames"]
        assert sum(r["links"].values()) >= 3  # cross-flight pairs found by retrieval
        assert r["ate_percent"] < 1.0 and r["rot_median_deg"] < 1.0
    acc = report["accuracy"]
    assert acc["ate_percent"] < 1.0 and set(acc["per_group"]) == {"0", "1"}


def test_the_reports_name_every_drone(swarm_run: Path) -> None:
    from dronecap.sfm.report import format_report

    text = format_report(json.loads((swarm_run / "sfm" / "report.json").read_text()))
    assert "drones: 2" in text and "drone_0:" in text and "drone_1:" in text
    from dronecap import figures  # the pipeline report's key figure of the sfm stage

    assert "2/2 drones in one model" in figures.sfm(swarm_run)


def test_a_single_flight_ground_truth_is_refused_for_a_swarm(swarm_run: Path, capsys) -> None:
    gt = swarm_run / "swarm" / "drone_0.json"
    out = swarm_run / "refused"
    argv = ["sfm", "--workdir", str(swarm_run), "--gt", str(gt), "--sfm-dir", str(out)]
    assert main([*argv, "-o", str(out / "posed.h5"), "--quiet"]) == 1
    assert "give the swarm.json" in capsys.readouterr().err
    assert not (out / "posed.h5").exists()


@pytest.mark.slow
def test_two_unrelated_flights_are_reported_apart(tmp_path: Path) -> None:
    """A corridor flight and an orbit flight given as two drones: neither lands in the other's
    model; the unlinked one is named and mapped on its own."""
    corridor, orbit = tmp_path / "corridor.mp4", tmp_path / "orbit.mp4"
    for scene, out in (("corridor", corridor), ("orbit", orbit)):
        argv = ["-q", "simulate", "--scene", scene, "--frames", "120", "-o", str(out)]
        assert main(argv) == 0
    assert main(["-q", "ingest", str(corridor), str(orbit), "-o", str(tmp_path / "f.h5")]) == 0
    sfm = ["sfm", "--frames", str(tmp_path / "f.h5"), "-o", str(tmp_path / "posed.h5")]
    assert main([*sfm, "--sfm-dir", str(tmp_path / "sfm"), "--quiet"]) == 0
    report = json.loads((tmp_path / "sfm" / "report.json").read_text())
    records = {r["name"]: r for r in report["drones"]}
    linked = [n for n, r in records.items() if r["linked"]]
    assert len(linked) == 1
    other = next(r for r in records.values() if not r["linked"])
    assert other["registered"] == 0 and other["own_model"]["frames"] >= 3
    assert (tmp_path / "sfm" / "work" / other["own_model"]["model"]).is_dir()
    posed = open_dataset(tmp_path / "posed.h5")
    assert set(posed.drones().tolist()) == {list(records).index(linked[0])}


@pytest.mark.slow
def test_the_front_end_on_a_local_ray_cluster_gives_the_same_model(swarm_run: Path) -> None:
    """`sfm --ray local`: each drone's features and own pairs as a Ray task (two workers, one
    per flight), the databases merged centrally; the model agrees with the local run's."""
    from dronecap.sfm.align import pose_accuracy

    out = swarm_run / "ray"
    argv = ["sfm", "--workdir", str(swarm_run), "--ray", "local", "--sfm-dir", str(out)]
    assert main([*argv, "-o", str(out / "posed.h5"), "--quiet"]) == 0
    report = json.loads((out / "report.json").read_text())
    assert report["matching"]["matcher"] == "pieces of flights (Ray tasks)"
    assert report["matching"]["cross_flight_pairs"] > 0
    local, ray = open_dataset(swarm_run / "posed.h5"), open_dataset(out / "posed.h5")

    def keys(ds):
        return list(zip(ds.drones().tolist(), ds.source_index.tolist(), strict=True))

    both = sorted(set(keys(local)) & set(keys(ray)))
    assert len(both) >= 0.95 * len(keys(local))
    a = np.stack([local.poses[keys(local).index(k)] for k in both])
    b = np.stack([ray.poses[keys(ray).index(k)] for k in both])
    agree = pose_accuracy(b, a)
    assert agree.ate_percent < 0.5 and agree.rot_median_deg < 0.5
