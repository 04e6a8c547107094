"""Shared test set-up: headless Qt, a private cache directory, fixed seeds."""

import os

import numpy as np
import pytest

os.environ.setdefault("QT_QPA_PLATFORM", "offscreen")


@pytest.fixture(autouse=True)
def _private_cache_dir(tmp_path, monkeypatch):
    """Keep FFTW wisdom, remembered settings and configuration away from the user's and from other
    tests: each test starts from a clean settings directory (the window remembers its session there)."""
    monkeypatch.setenv("TIRDEFLECT_CACHE_DIR", str(tmp_path / "cache"))
    monkeypatch.setenv("TIRDEFLECT_CONFIG_DIR", str(tmp_path / "config"))


@pytest.fixture
def rng():
    """A seeded random generator: tests are repeatable."""
    return np.random.default_rng(12345)
