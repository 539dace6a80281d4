"""Shared pytest fixtures."""

from __future__ import annotations

from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
DATASETS = REPO.parent / "shared" / "datasets"


@pytest.fixture(scope="session")
def datasets_dir() -> Path:
    """``../shared/datasets`` beside the checkout; tests needing it skip when it is absent."""
    if not (DATASETS / "README.md").is_file():
        pytest.skip(f"real datasets not available at {DATASETS} (clone with ../shared beside the checkout)")
    return DATASETS
