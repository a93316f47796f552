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


def test_a_swarm_with_one_telemetry_frame_is_fitted_as_one():
    from dronecap.sfm.priors import fit_swarm_to_priors

    t = np.linspace(0, 1, 20)
    world = np.concatenate(
        [flight(np.stack([3 * t, np.sin(3 * t), 0.2 * t], 1)), flight(np.stack([3 + t, t, t], 1))]
    )
    drones = np.repeat([0, 1], 20)
    to_sfm = Similarity(rot("x", 70) @ rot("z", 20), np.array([1.0, -2.0, 0.5]), 0.5)
    fit, shared = fit_swarm_to_priors(to_sfm.apply_poses(world), world, drones)
    assert shared and fit.sim.scale == pytest.approx(2.0, rel=1e-6)
    assert np.allclose(fit.sim.apply_poses(to_sfm.apply_poses(world)), world, atol=1e-6)


def test_a_swarm_whose_drones_have_their_own_origins_keeps_scale_and_gravity():
    from dronecap.sfm.priors import fit_swarm_to_priors

    t = np.linspace(0, 1, 20)
    world = np.concatenate(
        [flight(np.stack([3 * t, np.sin(3 * t), 0.2 * t], 1)), flight(np.stack([3 + t, t, t], 1))]
    )
    drones = np.repeat([0, 1], 20)
    # drone 1's onboard state: its own take-off point and heading (yaw 40 deg, shifted)
    own = Similarity(rot("z", 40), np.array([-3.0, 1.0, 0.0]), 1.0)
    priors = world.copy()
    priors[20:] = own.apply_poses(world[20:])
    to_sfm = Similarity(rot("x", 70) @ rot("z", 20), np.array([1.0, -2.0, 0.5]), 0.5)
    sfm = to_sfm.apply_poses(world)
    fit, shared = fit_swarm_to_priors(sfm, priors, drones)
    assert not shared and fit.method == "scale+gravity"
    assert fit.sim.scale == pytest.approx(2.0, rel=1e-6)
    metric = fit.sim.apply_poses(sfm)
    # metres: every distance as in the world; gravity: heights differ as in the world
    d_world = np.linalg.norm(world[0, :3, 3] - world[-1, :3, 3])
    assert np.linalg.norm(metric[0, :3, 3] - metric[-1, :3, 3]) == pytest.approx(d_world)
    dz = metric[:, 2, 3] - metric[0, 2, 3]
    assert np.allclose(dz, world[:, 2, 3] - world[0, 2, 3], atol=1e-6)
