"""Shared test fixtures: where the real data lives, and a skip when it is absent."""

from __future__ import annotations

from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
SHARED_DATA = REPO.parent / "shared" / "data"
LEGO_DIR = SHARED_DATA / "nerf_synthetic_160" / "lego"


@pytest.fixture(scope="session")
def lego_dir() -> Path:
    """The real 160x160 lego scene (Blender layout); skips when ../shared/data is absent."""
    if not (LEGO_DIR / "transforms_train.json").exists():
        pytest.skip(f"real lego data not found at {LEGO_DIR} (../shared/data is not checked out)")
    return LEGO_DIR
