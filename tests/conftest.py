"""Shared pytest configuration: hypothesis profiles and seeded generators."""

import shutil
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, settings

settings.register_profile(
    "ci", max_examples=60, deadline=None, derandomize=True,
    suppress_health_check=[HealthCheck.too_slow],
)
settings.load_profile("ci")


@pytest.fixture
def rng() -> np.random.Generator:
    """A fresh generator with a fixed seed, so every test is reproducible."""
    return np.random.default_rng(20240101)


@pytest.fixture()
def run_copy(finished: Path, tmp_path: Path) -> Path:
    """A copy of the test module's ``finished`` run directory (each module defines its own run)."""
    out = tmp_path / "run"
    shutil.copytree(finished, out)
    return out
