"""Many logs at once: ``decod batch`` (every log, one output directory each, a summary) and
``decod sweep`` (every log at every setting of a parameter grid, extraction shared), on Dask
or a local process pool (:mod:`decod_rs.batch.engine`).

```python
from pathlib import Path
from decod_rs.batch import RunOptions, build_jobs, open_engine, run_batch

jobs = build_jobs(["runs/"], None, RunOptions(preset="pipe", plots=False))
with open_engine() as engine:                 # dask LocalCluster, or a process pool
    result = run_batch(jobs, Path("out"), engine)
print(result.failed, result.rows[0]["accepted"])
```
"""

import importlib
from typing import TYPE_CHECKING, Any

from decod_rs.batch.engine import ENGINES, Engine, dask_available, open_engine
from decod_rs.batch.grid import Setting, parse_param, settings_from_grid
from decod_rs.batch.jobs import LogJob, RunOptions, build_jobs, discover_logs
from decod_rs.batch.manifest import Manifest, ManifestError, load_manifest

if TYPE_CHECKING:
    from decod_rs.batch.batch import BatchResult, LogOutcome, run_batch
    from decod_rs.batch.replay import Extraction, extract_log, run_from_extraction
    from decod_rs.batch.sweep import SweepResult, run_sweep

#: What runs logs (and so imports the pipeline and GTSAM) is imported when first used: the
#: command line's options and manifests (``decod batch --help``) do not wait for it.
_RUNNERS = {
    "BatchResult": "batch",
    "LogOutcome": "batch",
    "run_batch": "batch",
    "Extraction": "replay",
    "extract_log": "replay",
    "run_from_extraction": "replay",
    "SweepResult": "sweep",
    "run_sweep": "sweep",
}


def __getattr__(name: str) -> Any:
    module = _RUNNERS.get(name)
    if module is None:
        raise AttributeError(f"module 'decod_rs.batch' has no attribute {name!r}")
    return getattr(importlib.import_module(f"decod_rs.batch.{module}"), name)


__all__ = [
    "ENGINES",
    "BatchResult",
    "Engine",
    "Extraction",
    "LogJob",
    "LogOutcome",
    "Manifest",
    "ManifestError",
    "RunOptions",
    "Setting",
    "SweepResult",
    "build_jobs",
    "dask_available",
    "discover_logs",
    "extract_log",
    "load_manifest",
    "open_engine",
    "parse_param",
    "run_batch",
    "run_from_extraction",
    "run_sweep",
    "settings_from_grid",
]
