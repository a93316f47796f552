"""The federated tests reuse the trainer tests' analytic cube scene."""

from tests.nerf.conftest import cube_rgb  # noqa: F401  (a pytest fixture)
