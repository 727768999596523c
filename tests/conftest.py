"""Shared fixtures: the repository root and the default configuration."""

from pathlib import Path

import pytest

from hwp_tes_systematics.config import load_config

REPO = Path(__file__).resolve().parents[1]
DEFAULT_CONFIG = REPO / "config" / "config.yaml"


@pytest.fixture(scope="session")
def repo() -> Path:
    return REPO


@pytest.fixture
def default_config(monkeypatch) -> dict:
    """The embedded default configuration, read with the repository as working directory."""
    monkeypatch.chdir(REPO)
    return load_config(DEFAULT_CONFIG)
