"""decod: DeCOD loop closure for LiDAR SLAM in pipes and tunnels.

The heavy lifting (submaps, descriptors, matching, MCAP reading) runs in the Rust extension
``decod_rs._core``; this package wraps it in typed Python and adds the GTSAM pose graph,
evaluation, the simulator and the ``decod`` command.
"""

from decod_rs._core import (
    ConfigError,
    DatabaseError,
    InternalError,
    Landmark,
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
    "Landmark",
    "LogFormatError",
    "TopicError",
    "UnsupportedMessageError",
    "__version__",
    "dump_config",
    "load_config",
]
# Each layer appends its public names below (one block per layer keeps merges clean).

# --- matching (issue 5) ---
from decod_rs.matching import (
    LandmarkDatabase,
    PairResult,
    QueryResult,
    compare,
    synthetic_landmark,
)

__all__ += ["LandmarkDatabase", "PairResult", "QueryResult", "compare", "synthetic_landmark"]
