"""Shared fixtures: the real photographs shipped with the tests."""

from __future__ import annotations

from pathlib import Path

import pytest

DATA = Path(__file__).parent / "data"


@pytest.fixture
def data_dir() -> Path:
    """Folder of real photographs: img_example.pgm (target) and the near/far pair."""
    return DATA
