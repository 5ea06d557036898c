"""Wall time of ``decod batch`` on N logs against N sequential ``run_log`` calls
(pytest-benchmark; ``make bench`` only: not collected when benchmarks are disabled, see
``conftest.py``).

The logs: N = 4 simulated hume pipes (seeds 0-3, 60 m out and back as in the README's
table, pipe preset, no plots; about 5 s each on two cores). The batch runs on the default
engine (Dask's LocalCluster when the batch extra is installed, else the process pool) with
one worker per core; its figure includes starting and stopping the cluster, as a user's
``decod batch`` does, and ``test_engine_start_and_stop`` measures that overhead alone.
"""

from __future__ import annotations

from pathlib import Path

import pytest
from pytest_benchmark.fixture import BenchmarkFixture

from decod_rs.batch.batch import run_batch
from decod_rs.batch.engine import cores, open_engine
from decod_rs.batch.jobs import LogJob, RunOptions
from decod_rs.pipeline import run_log
from decod_rs.sim import simulate

N_LOGS = 4
LENGTH_M = 60.0
OPTIONS = RunOptions(preset="pipe", imu_topic="/imu", plots=False)


@pytest.fixture(scope="module")
def logs(tmp_path_factory: pytest.TempPathFactory) -> list[Path]:
    root = tmp_path_factory.mktemp("bench_logs")
    for seed in range(N_LOGS):
        simulate("hume", root / f"s{seed}", seed=seed, length_m=LENGTH_M, progress=False)
    return [root / f"s{seed}" / "log" for seed in range(N_LOGS)]


def test_batch_of_n_logs(benchmark: BenchmarkFixture, logs: list[Path], tmp_path: Path) -> None:
    jobs = [LogJob(f"log{k}", log, OPTIONS) for k, log in enumerate(logs)]

    def batch() -> int:
        with open_engine("auto", workers=cores()) as engine:
            benchmark.extra_info["engine"] = engine.description
            return run_batch(jobs, tmp_path / "batch", engine, force=True).failed

    assert benchmark.pedantic(batch, rounds=2, iterations=1) == 0
    benchmark.extra_info.update(logs=N_LOGS, cores=cores())


def test_n_sequential_runs(benchmark: BenchmarkFixture, logs: list[Path], tmp_path: Path) -> None:
    def sequential() -> int:
        for k, log in enumerate(logs):
            run_log(log, tmp_path / f"log{k}", **OPTIONS.run_kwargs())
        return len(logs)

    assert benchmark.pedantic(sequential, rounds=2, iterations=1) == N_LOGS
    benchmark.extra_info.update(logs=N_LOGS, cores=cores())


def test_engine_start_and_stop(benchmark: BenchmarkFixture, logs: list[Path]) -> None:
    def start_stop() -> int:
        with open_engine("auto", workers=cores()) as engine:
            return engine.workers

    assert benchmark.pedantic(start_stop, rounds=3, iterations=1) == cores()
