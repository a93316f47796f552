"""Telemetry priors: the similarity from an SfM frame to the priors' metric, z-up world."""

from __future__ import annotations

import numpy as np
import pytest

from dronecap.datasets.format import Dataset
from dronecap.sfm.align import DegenerateAlignment, Similarity
from dronecap.sfm.priors import fit_to_priors, read_priors


def rot(axis: str, deg: float) -> np.ndarray:
    a = np.radians(deg)
    c, s = np.cos(a), np.sin(a)
    i, j = {"x": (1, 2), "y": (2, 0), "z": (0, 1)}[axis]
    r = np.eye(3)
    r[i, i], r[i, j], r[j, i], r[j, j] = c, -s, s, c
    return r


def flight(centres: np.ndarray) -> np.ndarray:
    """Forward-looking cameras (OpenCV axes: z forward, y down) at ``centres`` in a z-up world,
    yawing slowly."""
    body_from_cam = np.array([[0, 0, 1], [-1, 0, 0], [0, -1, 0]], float)  # the contract's
    out = np.tile(np.eye(4), (len(centres), 1, 1))
    for i, c in enumerate(centres):
        out[i, :3, :3] = rot("z", 3.0 * i) @ body_from_cam
        out[i, :3, 3] = c
    return out


# what SfM would return: the world flight seen through an arbitrary similarity
TRUE = Similarity(rot("x", 70) @ rot("z", -40), np.array([0.3, -2.0, 5.0]), 0.37)


def sfm_view(world: np.ndarray) -> np.ndarray:
    inv_r = TRUE.rotation.T
    out = world.copy()
    out[:, :3, :3] = inv_r @ world[:, :3, :3]
    out[:, :3, 3] = (world[:, :3, 3] - TRUE.translation) @ TRUE.rotation / TRUE.scale
    return out


def test_exact_priors_give_back_the_similarity():
    t = np.linspace(0, 1, 12)
    world = flight(np.stack([3 * t, np.sin(3 * t), 1 + 0.2 * t], 1))
    fit = fit_to_priors(sfm_view(world), world)
    assert fit.method == "positions" and fit.used.all()
    assert fit.sim.scale == pytest.approx(TRUE.scale, rel=1e-9)
    assert np.allclose(fit.sim.rotation, TRUE.rotation, atol=1e-9)
    agree = fit.agreement(sfm_view(world), world)
    assert agree["position_rmse_m"] < 1e-9 and agree["rotation_median_deg"] < 1e-5


def test_a_telemetry_glitch_is_trimmed():
    t = np.linspace(0, 1, 20)
    world = flight(np.stack([4 * t, np.cos(4 * t), 1 + 0.5 * t**2], 1))
    noisy = world.copy()
    noisy[:, :3, 3] += np.random.default_rng(0).normal(0, 0.01, (20, 3))  # 1 cm noise
    noisy[7, :3, 3] += [0.0, 0.0, 2.0]  # a 2 m glitch
    fit = fit_to_priors(sfm_view(world), noisy)
    assert not fit.used[7] and fit.used.sum() >= 17
    assert fit.sim.scale == pytest.approx(TRUE.scale, rel=0.01)
    # gravity: world +z seen from the SfM frame maps back onto +z
    up = fit.sim.rotation @ (TRUE.rotation.T @ np.array([0, 0, 1.0]))
    assert np.degrees(np.arccos(np.clip(up[2], -1, 1))) < 1.0


def test_a_straight_flight_takes_its_rotation_from_the_orientations():
    t = np.linspace(0, 2, 10)
    world = flight(np.stack([t, 0.5 * t, 1 + 0 * t], 1))  # collinear centres
    fit = fit_to_priors(sfm_view(world), world)
    assert fit.method == "orientations+positions"
    assert np.allclose(fit.sim.rotation, TRUE.rotation, atol=1e-9)
    assert fit.sim.scale == pytest.approx(TRUE.scale, rel=1e-9)


def test_too_few_or_coincident_priors_are_degenerate():
    world = flight(np.zeros((5, 3)))
    with pytest.raises(DegenerateAlignment):
        fit_to_priors(sfm_view(world), world)
    with pytest.raises(DegenerateAlignment, match="need 3"):
        fit_to_priors(sfm_view(world[:2]), world[:2])


def test_read_priors_needs_both_arrays_and_a_valid_row():
    ds = Dataset(images=np.zeros((3, 8, 8, 1), np.uint8), kind="frames")
    assert read_priors(ds) is None
    ds.extra["prior_c2w"] = np.tile(np.eye(4), (3, 1, 1))
    ds.extra["prior_valid"] = np.zeros(3, bool)
    assert read_priors(ds) is None
    ds.extra["prior_valid"] = np.array([True, False, True])
    ds.extra["prior_c2w"][2, 0, 3] = np.nan
    c2w, valid = read_priors(ds)
    assert valid.tolist() == [True, False, False] and c2w.shape == (3, 4, 4)
