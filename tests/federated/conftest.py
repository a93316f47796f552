"""The federated tests reuse the trainer tests' analytic cube scene."""

from tests.nerf.conftest import cube_rgb, make_cube  # noqa: F401  (pytest fixtures)
