"""Shared test fixtures.

``shared_data_dir`` points at ``../shared/data`` (or ``$DERENDER_SHARED_DATA``). Tests
that need it skip with a reason when it is absent, unless
``DERENDER_REQUIRE_SHARED_DATA=1`` (set by ``.ci/run``), which turns the skip into a
failure.
"""

from __future__ import annotations

import os
from pathlib import Path

import pytest

REPO_ROOT = Path(__file__).resolve().parents[1]


def _shared_data_root() -> Path:
    env = os.environ.get("DERENDER_SHARED_DATA")
    if env:
        return Path(env)
    return REPO_ROOT.parent / "shared" / "data"


def require_shared(subdir: str) -> Path:
    """Return ``shared/data/<subdir>``, skipping (or failing under CI) when absent."""
    path = _shared_data_root() / subdir
    if not path.is_dir():
        msg = f"shared test data not found: {path} (see shared/data/README.md)"
        if os.environ.get("DERENDER_REQUIRE_SHARED_DATA") == "1":
            pytest.fail(msg + "; DERENDER_REQUIRE_SHARED_DATA=1 makes it mandatory")
        pytest.skip(msg)
    return path


@pytest.fixture
def memorial_dir() -> Path:
    return require_shared("debevec-memorial")


@pytest.fixture
def frobisher_dir() -> Path:
    return require_shared("colour-hdri-frobisher")


@pytest.fixture
def colorchecker_dng() -> Path:
    return require_shared("colorchecker-raw-dng") / "colorchart.dng"


@pytest.fixture
def rawtoaces_dir() -> Path:
    return require_shared("rawtoaces-spectral")
