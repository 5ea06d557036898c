"""Benchmarks that cost minutes of wall time are benchmarks only: collected by `make bench`
(`--benchmark-enable`), not by the test run, where they would measure nothing (timing is
disabled there) and only cost time. Cheap benchmarks (the pose graph) still run once in the
test run as smoke tests."""

from __future__ import annotations

from pathlib import Path

import pytest

#: Modules that simulate logs of their own (the batch benchmark: 4 x 60 m logs, ~2 min).
BENCHMARK_ONLY = {"test_batch_bench.py"}


def pytest_ignore_collect(collection_path: Path, config: pytest.Config) -> bool | None:
    if collection_path.name not in BENCHMARK_ONLY:
        return None
    disabled = config.getoption("benchmark_disable") and not config.getoption("benchmark_enable")
    return True if disabled else None
