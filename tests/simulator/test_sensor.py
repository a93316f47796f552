"""Lens and sensor defects of the simulator: each measurably present at its default level, absent
when off, and the ground truth exact (checked against OpenCV's camera maths and by hand)."""

from __future__ import annotations

import dataclasses

import cv2
import numpy as np
import pytest

from dronecap.camera import Camera
from dronecap.simulator.flights import camera_to_world
from dronecap.simulator.render import Renderer
from dronecap.simulator.scenes import Scene, quad_mesh
from dronecap.simulator.sensor import (
    DEFECT_DEFAULTS,
    Sensor,
    default_lens,
    jpeg_roundtrip,
    sensor_preset,
    vignette,
    with_lens_defects,
)
from dronecap.simulator.simulate import Capture, SimulatedFlight, capture_preset

K1, K2 = DEFECT_DEFAULTS["distortion"]
NOISE_FREE = Sensor(read_noise=0.0, shot_noise=0.0)


def edge_scene() -> Scene:
    """A wall at world x = 2 m facing a camera at the origin; its albedo ramps from 1 to 0 across
    the vertical line y = -1 m (0.05 m wide), which the camera sees at normalised x = 0.5."""

    def ramp(points: np.ndarray, normals: np.ndarray, footprint: np.ndarray) -> np.ndarray:
        return np.clip(0.5 + (points[1] + 1.0) / 0.05, 0.0, 1.0).astype(np.float32)

    wall = quad_mesh([(2.0, -3.0, -3.0), (2.0, 3.0, -3.0), (2.0, 3.0, 3.0), (2.0, -3.0, 3.0)])
    return Scene("edge", [wall], [ramp], [], ambient=1.0)


def edge_columns(image: np.ndarray) -> np.ndarray:
    """Continuous x (pixel centres at +0.5) where each row crosses 0.5 going right: [H]."""
    out = []
    for row in image:
        j = int(np.flatnonzero((row[:-1] >= 0.5) & (row[1:] < 0.5))[0])
        out.append(j + 0.5 + (row[j] - 0.5) / (row[j] - row[j + 1]))
    return np.asarray(out)


LENSES = {
    "pinhole": default_lens(160, 160),
    "distorted": with_lens_defects(default_lens(160, 160), (K1, K2)),
    "distorted, off centre": with_lens_defects(
        default_lens(160, 160), (K1, K2), DEFECT_DEFAULTS["principal_offset"]
    ),
}


@pytest.mark.parametrize("name", list(LENSES))
def test_rendered_edge_is_where_the_lens_model_puts_it(name):
    """A straight vertical edge: every row's crossing, undistorted through the lens, lies on the
    edge's ray (x/z = 0.5) to 0.05 px; distorted lenses curve it by pixels, the pinhole does not."""
    lens = LENSES[name]
    c2w = camera_to_world(np.zeros((1, 3)), np.zeros(1), np.zeros(1), np.zeros(1))
    image = Renderer(edge_scene(), lens).radiance(c2w)[0]
    cols = edge_columns(image)
    rows = np.arange(lens.height) + 0.5
    xy = lens.undistort_points(np.stack([cols, rows], 1))
    np.testing.assert_allclose(xy[:, 0], 0.5, atol=0.05 / lens.fx)
    bend = cols.max() - cols.min()
    if lens.is_pinhole:
        assert bend < 0.05
        assert cols.mean() == pytest.approx(lens.cx + 0.5 * lens.fx, abs=0.05)
    else:  # barrel distortion pulls the edge's ends towards the centre: by hand, x = 0.5 at
        # y = 0 (r^2 = 0.25) lands at 0.5 * 0.976 * fx = 58.6 px from cx, at the top row
        # (y = -0.66, r^2 = 0.69) at 0.5 * 0.941 * fx = 56.4 px: a bend of ~2.2 px
        assert bend > 2.0
        # the same points projected by OpenCV itself
        pts = np.stack([np.full_like(xy[:, 1], 0.5), xy[:, 1], np.ones_like(rows)], 1)
        proj, _ = cv2.projectPoints(pts, np.zeros(3), np.zeros(3), lens.matrix(),
                                    lens.opencv_coeffs())  # fmt: skip
        np.testing.assert_allclose(proj[:, 0, 0], cols, atol=0.05)


def test_flight_json_intrinsics_follow_the_contract():
    sim = SimulatedFlight("corridor", 10, 0, capture_preset("aideck"))
    k = sim.document()["intrinsics"]
    assert (k["width"], k["height"], k["fx"]) == (324, 244, 184.0)
    assert k["model"] == "pinhole" and k["distortion"] == [K1, K2, 0.0, 0.0, 0.0]
    dx, dy = DEFECT_DEFAULTS["principal_offset"]
    assert (k["cx"], k["cy"]) == (pytest.approx(162 + dx * 324), pytest.approx(122 + dy * 244))
    cam = Camera.from_opencv(
        np.array([[k["fx"], 0, k["cx"]], [0, k["fy"], k["cy"]], [0, 0, 1]]),
        k["distortion"], k["width"], k["height"],
    )  # fmt: skip
    assert cam.opencv_coeffs()[:2].tolist() == [K1, K2]
    clean = SimulatedFlight("corridor", 10, 0, Capture()).document()["intrinsics"]
    assert "distortion" not in clean and clean["fx"] == 120.0


def render(capture: Capture, s: int, frames: int = 30) -> np.ndarray:
    return SimulatedFlight("corridor", frames, 0, capture).render_source(s).astype(np.float64)


def test_vignetting_darkens_the_corners_by_its_level():
    v = float(DEFECT_DEFAULTS["vignetting"])
    lens = Sensor().lens
    m = vignette(lens, v)
    assert m[80, 80] == pytest.approx(1.0, abs=1e-3)
    assert m[0, 0] == pytest.approx(1 - v * (79.5**2 * 2) / (80**2 * 2), abs=1e-6)
    flat = render(Capture(NOISE_FREE), 5)
    dark = render(Capture(dataclasses.replace(NOISE_FREE, vignetting=v)), 5)
    ok = (flat > 20) & (flat < 250)  # lit, not clipped
    ratio = dark[ok] / flat[ok]
    np.testing.assert_allclose(ratio, m[ok], atol=1 / 20)  # two roundings of 0.5 DN, DN > 20
    assert np.median((dark / np.maximum(flat, 1))[:10, :10][flat[:10, :10] > 20]) < 1 - 0.8 * v


@pytest.mark.parametrize("level", ["default", "clean"])
def test_noise_variance_matches_the_model(level):
    read, shot = DEFECT_DEFAULTS["noise"] if level == "default" else (1.5, 0.04)
    clean = render(Capture(NOISE_FREE), 7)
    noisy = render(Capture(dataclasses.replace(NOISE_FREE, read_noise=read, shot_noise=shot)), 7)
    diff = noisy - clean
    for lo, hi in ((30, 70), (110, 170)):
        sel = (clean >= lo) & (clean < hi)
        assert sel.sum() > 1500
        model = np.mean(shot * clean[sel] + read**2) + 2 / 12  # + both quantisations
        assert np.var(diff[sel]) == pytest.approx(model, rel=0.12)


def test_motion_blur_follows_the_exposure_time():
    def sharpness(img: np.ndarray) -> float:
        return float(cv2.Laplacian(img, cv2.CV_64F).var())

    short = render(Capture(NOISE_FREE), 14)
    ms = float(DEFECT_DEFAULTS["blur"])
    blurred_sensor = dataclasses.replace(NOISE_FREE, exposure_s=ms / 1000, max_subframes=16)
    long = render(Capture(blurred_sensor), 14)
    assert sharpness(long) < 0.8 * sharpness(short)
    assert abs(long.mean() - short.mean()) < 2.0  # same light, only smeared


def test_exposure_drift_scales_the_frames_by_the_gain():
    drift = float(DEFECT_DEFAULTS["exposure_drift"])
    cap = Capture(dataclasses.replace(NOISE_FREE, exposure_drift=drift))
    sim = SimulatedFlight("corridor", 30, 0, cap)
    gains = sim.gain
    assert gains.max() / gains.min() > 1 + drift  # swings of +-35 % around 0.95
    clean = SimulatedFlight("corridor", 30, 0, Capture(NOISE_FREE))
    assert clean.gain.max() / clean.gain.min() < 1.25
    s = int(np.argmax(np.abs(gains - clean.gain)))
    a, b = render(Capture(NOISE_FREE), s), render(cap, s)
    ok = (a > 20) & (a < 160) & (b < 250)
    assert np.median(b[ok] / a[ok]) == pytest.approx(gains[s] / clean.gain[s], rel=0.01)


def test_jpeg_adds_block_artefacts():
    def blockiness(img: np.ndarray) -> float:
        d = np.abs(np.diff(img.astype(np.float64), axis=1))
        edge = d[:, 7::8].mean()
        inside = np.delete(d, np.s_[7::8], axis=1).mean()
        return float(edge / inside)

    raw = render(Capture(Sensor(read_noise=3.0, shot_noise=0.3)), 9).astype(np.uint8)
    q = int(DEFECT_DEFAULTS["jpeg"])
    jpg = jpeg_roundtrip(raw, q)
    assert blockiness(raw) < 1.03
    assert blockiness(jpg) > 1.1
    assert 1.0 < np.abs(jpg.astype(int) - raw).mean() < 8.0
    cap = Capture(Sensor(read_noise=3.0, shot_noise=0.3, jpeg_quality=q))
    np.testing.assert_array_equal(render(cap, 9), jpg)


def test_aideck_preset_renders_its_size_with_every_defect():
    sensor = sensor_preset("aideck")
    assert not sensor.problems()
    assert sensor.lens.model == "RADIAL" and sensor.vignetting > 0 and sensor.jpeg_quality
    frame = SimulatedFlight("corridor", 30, 0, capture_preset("aideck")).render_source(3)
    assert frame.shape == (244, 324) and frame.dtype == np.uint8 and frame.std() > 15
    small = sensor_preset("aideck-162").lens
    assert (small.width, small.height, small.fx) == (162, 162, 92.0)
