"""Shared fixtures: the real photographs shipped with the tests, a private data folder and a fresh "psfd" logger per
test; slow tests' time limit."""

from __future__ import annotations

import logging
from pathlib import Path

import pytest

DATA = Path(__file__).parent / "data"


@pytest.fixture(autouse=True)
def private_data_home(tmp_path_factory, monkeypatch) -> Path:
    """Every test gets its own $XDG_DATA_HOME: the user's catalogue and the simulated rig's state
    (sim-rig.json) never leak between tests or into the home folder of whoever runs them."""
    home = tmp_path_factory.mktemp("data-home")
    monkeypatch.setenv("XDG_DATA_HOME", str(home))
    return home


@pytest.fixture
def data_dir() -> Path:
    """Folder of real photographs: img_example.pgm (target) and the near/far pair."""
    return DATA


@pytest.fixture(autouse=True)
def psfd_logger_restored():
    """A command run in-process (`psfd.cli.main`) points the "psfd" logger at that moment's stderr and stops it
    propagating (`psfd.cli.logs.setup`): left so, a later test's ``caplog`` saw none of psfd's records (its
    asserts on a record failed, its asserts that none came passed whatever happened) and the records went to a
    stream pytest had closed. Each test starts from the logger as the test session found it."""
    logger = logging.getLogger("psfd")
    saved = logger.handlers[:], logger.level, logger.propagate
    yield
    logger.handlers[:], logger.level, logger.propagate = saved


def pytest_collection_modifyitems(config, items):
    """A slow test (`-m slow`: whole 24-megapixel frames, renders, fresh installs) may take longer than the default
    suite's limit per test (pyproject.toml's ``timeout``): 30 minutes, unless it sets its own."""
    for item in items:
        if item.get_closest_marker("slow") and not item.get_closest_marker("timeout"):
            item.add_marker(pytest.mark.timeout(1800))
