"""Shared fixtures: simulated logs are large (150-300 MB of MCAP each), so disk is freed as
soon as a module is done with them (``module_dir``), and pyproject's
``tmp_path_retention_policy = "failed"`` drops each passing test's ``tmp_path``. A module
with a failure keeps its data for inspection."""

from __future__ import annotations

import shutil
from collections.abc import Iterator
from pathlib import Path

import pytest


@pytest.fixture(scope="module")
def module_dir(
    request: pytest.FixtureRequest, tmp_path_factory: pytest.TempPathFactory
) -> Iterator[Path]:
    """A scratch folder for one test module's shared logs, removed after its last test unless
    one of its tests failed."""
    name = request.module.__name__.rsplit(".", 1)[-1]
    path = tmp_path_factory.mktemp(name)
    failed_before = request.session.testsfailed
    yield path
    if request.session.testsfailed == failed_before:
        shutil.rmtree(path, ignore_errors=True)
