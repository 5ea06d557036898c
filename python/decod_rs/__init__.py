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

# Pose graph, TUM files, run files, evaluation and plots (issue 6: graph).
from decod_rs.evaluate import evaluate_run, format_table
from decod_rs.graph import (
    CorrectionResult,
    GraphResult,
    LoopConstraint,
    correct_trajectory,
    optimize,
    propagate_to_scans,
)
from decod_rs.graph_export import write_g2o, write_graph_json
from decod_rs.run_files import (
    LandmarkTable,
    LoopTable,
    loops_to_constraints,
    read_landmarks_csv,
    read_loops_csv,
    write_landmarks_csv,
    write_loops_csv,
)
from decod_rs.tum import interpolate_poses, read_tum, write_tum

__all__ += [
    "CorrectionResult",
    "GraphResult",
    "LandmarkTable",
    "LoopConstraint",
    "LoopTable",
    "correct_trajectory",
    "evaluate_run",
    "format_table",
    "interpolate_poses",
    "loops_to_constraints",
    "optimize",
    "propagate_to_scans",
    "read_landmarks_csv",
    "read_loops_csv",
    "read_tum",
    "write_g2o",
    "write_graph_json",
    "write_landmarks_csv",
    "write_loops_csv",
    "write_tum",
]

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
]

# --- extraction (issue 2) -----------------------------------------------------------------
from decod_rs.extraction import (
    ExtractionResult,
    Rejection,
    Submap,
    SubmapBuilder,
    SubmapDiagnostics,
    build_submap,
    extract_landmarks,
    extract_submap,
    extract_submaps,
    submap_builder,
    submap_from_points,
)

__all__ += [
    "ExtractionResult",
    "Rejection",
    "Submap",
    "SubmapBuilder",
    "SubmapDiagnostics",
    "build_submap",
    "extract_landmarks",
    "extract_submap",
    "extract_submaps",
    "submap_builder",
    "submap_from_points",
]

# --- matching (issue 5) ---
from decod_rs.matching import (
    LandmarkDatabase,
    PairResult,
    QueryResult,
    compare,
    synthetic_landmark,
)

__all__ += ["LandmarkDatabase", "PairResult", "QueryResult", "compare", "synthetic_landmark"]

# Real logs as they come (issue 11): damage, odometry gaps, unusable clouds.
from decod_rs.ingest import LogFaultInfo, LogWarning, StreamHealth

__all__ += ["LogFaultInfo", "LogWarning", "StreamHealth"]
