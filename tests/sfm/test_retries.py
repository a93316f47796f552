"""Which remedies a failed first attempt tries, in which order, and what each one changes."""

from __future__ import annotations

import json

import numpy as np
import pytest

from dronecap.camera import Camera
from dronecap.cli import main as cli_main
from dronecap.datasets.format import Dataset, write_dataset
from dronecap.sfm.camera_plan import CameraPlan
from dronecap.sfm.options import SfmOptions
from dronecap.sfm.retries import remedies

KNOWN = Camera(90.0, 90.0, 81.0, 100.0, 160, 160)


def test_remedies_in_order_and_what_they_change():
    opts = SfmOptions(matcher="sequential", max_features=1000, peak_threshold=0.004)
    estimate = CameraPlan("estimate", None, "none")
    fixed = CameraPlan("fixed", KNOWN, "calibration")
    found = remedies(opts, estimate, fixed, 120)
    names = [n for n, _ in found]
    assert names == [
        "exhaustive matching",
        "contrast normalisation (CLAHE)",
        "more features",
        "finer SIFT scales",
        "known camera, fixed",
    ]
    o, p = opts, estimate
    for _, change in found:  # applied one on top of the other
        o, p = change(o, p)
    assert o.matcher == "exhaustive" and o.clahe
    assert (o.max_features, o.peak_threshold) == (2000, 0.002)
    assert o.first_octave == -2  # the default -1 upsamples 2x; the remedy 4x
    assert p is fixed


def test_remedies_that_do_not_apply_are_skipped():
    opts = SfmOptions(matcher="exhaustive", clahe=True)
    fixed = CameraPlan("fixed", KNOWN, "calibration")
    assert [n for n, _ in remedies(opts, fixed, None, 50)] == ["more features", "finer SIFT scales"]
    finest = SfmOptions(matcher="exhaustive", clahe=True, first_octave=-2)
    assert [n for n, _ in remedies(finest, fixed, None, 50)] == ["more features"]
    # too many frames for exhaustive matching to be a remedy
    seq = SfmOptions(matcher="sequential")
    assert "exhaustive matching" not in [n for n, _ in remedies(seq, fixed, None, 1000)]


@pytest.mark.parametrize("finer_below", [0, 400])
def test_a_failed_flight_reports_every_attempt(tmp_path, finer_below):
    """Noise frames never register: every remedy that applies is tried. Pixel noise gives few
    SIFT blobs at octave -1, so by default the first attempt already extracts at -2 and finer
    scales are not a remedy; with --finer-below 0 they are."""
    rng = np.random.default_rng(0)
    noise = rng.integers(0, 256, (5, 160, 160, 1), dtype=np.uint8)  # nothing matches
    write_dataset(tmp_path / "frames.h5", Dataset(images=noise, kind="frames"))
    argv = ["sfm", "--workdir", str(tmp_path), "--quiet", "--threads", "1"]
    assert cli_main([*argv, "--finer-below", str(finer_below)]) == 1
    report = json.loads((tmp_path / "sfm" / "report.json").read_text())
    tried = [None, "contrast normalisation (CLAHE)", "more features"]
    if finer_below == 0:
        tried.append("finer SIFT scales")
    assert [a["remedies"][-1] if a["remedies"] else None for a in report["attempts"]] == tried
    assert report["sift_first_octave"] == (-1 if finer_below == 0 else -2)
    works = ["work", "work_retry1", "work_retry2", "work_retry3"][: len(tried)]
    assert [a["work"] for a in report["attempts"]] == works
