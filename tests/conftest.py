"""Shared test fixtures: the real data folder and the hardware marker."""
from __future__ import annotations

import os
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]


def shared_data_dir() -> Path | None:
    """``../shared/data`` beside the checkout (or $MOCAP_SHARED_DATA); None when absent."""
    env = os.environ.get("MOCAP_SHARED_DATA")
    cand = Path(env) if env else REPO.parent / "shared" / "data"
    return cand if cand.is_dir() else None


@pytest.fixture(scope="session")
def shared_data() -> Path:
    d = shared_data_dir()
    if d is None:
        pytest.skip("../shared/data not present (real-data tests skip cleanly)")
    return d


def pytest_addoption(parser):
    parser.addoption("--run-hardware", action="store_true", default=False,
                     help="run tests marked 'hardware' (needs cameras / sync box attached)")


def pytest_collection_modifyitems(config, items):
    if config.getoption("--run-hardware"):
        return
    skip = pytest.mark.skip(reason="hardware test: run with --run-hardware and devices attached")
    for item in items:
        if "hardware" in item.keywords:
            item.add_marker(skip)
