"""decod: DeCOD loop closure for LiDAR SLAM in pipes and tunnels.

The heavy lifting (submaps, descriptors, matching, MCAP reading) runs in the Rust extension
``decod_rs._core``; this package wraps it in typed Python and adds the GTSAM pose graph,
evaluation, the simulator and the ``decod`` command.
"""

from decod_rs._core import (
    ConfigError,
    DatabaseError,
    InternalError,
    LogFormatError,
    TopicError,
    UnsupportedMessageError,
    __version__,
)
from decod_rs.config import Config, dump_config, load_config

__all__ = [
    "Config",
    "ConfigError",
    "DatabaseError",
    "InternalError",
    "LogFormatError",
    "TopicError",
    "UnsupportedMessageError",
    "__version__",
    "dump_config",
    "load_config",
]
# Each layer appends its public names below (one block per layer keeps merges clean).

# --- io (issue 4) ---
from decod_rs.io import (
    LogInfo,
    ScanReader,
    ScanRecord,
    TopicCheck,
    TopicInfo,
    check_log,
    find_imu_topic,
    inspect_log,
    read_log,
    read_tum,
)

__all__ += [
    "LogInfo",
    "ScanReader",
    "ScanRecord",
    "TopicCheck",
    "TopicInfo",
    "check_log",
    "find_imu_topic",
    "inspect_log",
    "read_log",
    "read_tum",
]
