"""decod: DeCOD loop closure for LiDAR SLAM in pipes and tunnels.

The heavy lifting (submaps, descriptors, matching, MCAP reading) runs in the Rust extension
``decod_rs._core``; this package wraps it in typed Python and adds the GTSAM pose graph,
evaluation, the simulator and the ``decod`` command.
"""

import importlib
from typing import TYPE_CHECKING, Any

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

# The layers below are imported on first use (PEP 562): ``import decod_rs.recording`` in the
# recording's worker process, or ``decod --help``, need not load GTSAM (0.1 s) and the
# evaluation (0.3 s in all). Each layer lists its public names (one block per layer keeps
# merges clean); the same names are imported for type checkers below.
_LAZY: dict[str, str] = {}

# Pose graph, TUM files, run files, evaluation (issue 6: graph)
_LAZY.update(dict.fromkeys(["evaluate_run", "format_table"], "decod_rs.evaluate"))
_LAZY.update(
    dict.fromkeys(
        [
            "CorrectionResult",
            "GraphResult",
            "LoopConstraint",
            "correct_trajectory",
            "optimize",
            "propagate_to_scans",
        ],
        "decod_rs.graph",
    )
)
_LAZY.update(dict.fromkeys(["write_g2o", "write_graph_json"], "decod_rs.graph_export"))
_LAZY.update(
    dict.fromkeys(
        [
            "LandmarkTable",
            "LoopTable",
            "loops_to_constraints",
            "read_landmarks_csv",
            "read_loops_csv",
            "write_landmarks_csv",
            "write_loops_csv",
        ],
        "decod_rs.run_files",
    )
)
_LAZY.update(dict.fromkeys(["interpolate_poses", "read_tum", "write_tum"], "decod_rs.tum"))

# io (issue 4)
_LAZY.update(
    dict.fromkeys(
        [
            "LogInfo",
            "ScanReader",
            "ScanRecord",
            "TopicCheck",
            "TopicInfo",
            "check_log",
            "find_imu_topic",
            "inspect_log",
            "read_log",
        ],
        "decod_rs.io",
    )
)

# extraction (issue 2)
_LAZY.update(
    dict.fromkeys(
        [
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
        ],
        "decod_rs.extraction",
    )
)

# matching (issue 5)
_LAZY.update(
    dict.fromkeys(
        ["LandmarkDatabase", "PairResult", "QueryResult", "compare", "synthetic_landmark"],
        "decod_rs.matching",
    )
)

# Real logs as they come (issue 11): damage, odometry gaps, unusable clouds
_LAZY.update(dict.fromkeys(["LogFaultInfo", "LogWarning", "StreamHealth"], "decod_rs.ingest"))

if TYPE_CHECKING:
    from decod_rs.evaluate import (
        evaluate_run as evaluate_run,
    )
    from decod_rs.evaluate import (
        format_table as format_table,
    )
    from decod_rs.extraction import (
        ExtractionResult as ExtractionResult,
    )
    from decod_rs.extraction import (
        Rejection as Rejection,
    )
    from decod_rs.extraction import (
        Submap as Submap,
    )
    from decod_rs.extraction import (
        SubmapBuilder as SubmapBuilder,
    )
    from decod_rs.extraction import (
        SubmapDiagnostics as SubmapDiagnostics,
    )
    from decod_rs.extraction import (
        build_submap as build_submap,
    )
    from decod_rs.extraction import (
        extract_landmarks as extract_landmarks,
    )
    from decod_rs.extraction import (
        extract_submap as extract_submap,
    )
    from decod_rs.extraction import (
        extract_submaps as extract_submaps,
    )
    from decod_rs.extraction import (
        submap_builder as submap_builder,
    )
    from decod_rs.extraction import (
        submap_from_points as submap_from_points,
    )
    from decod_rs.graph import (
        CorrectionResult as CorrectionResult,
    )
    from decod_rs.graph import (
        GraphResult as GraphResult,
    )
    from decod_rs.graph import (
        LoopConstraint as LoopConstraint,
    )
    from decod_rs.graph import (
        correct_trajectory as correct_trajectory,
    )
    from decod_rs.graph import (
        optimize as optimize,
    )
    from decod_rs.graph import (
        propagate_to_scans as propagate_to_scans,
    )
    from decod_rs.graph_export import (
        write_g2o as write_g2o,
    )
    from decod_rs.graph_export import (
        write_graph_json as write_graph_json,
    )
    from decod_rs.ingest import (
        LogFaultInfo as LogFaultInfo,
    )
    from decod_rs.ingest import (
        LogWarning as LogWarning,
    )
    from decod_rs.ingest import (
        StreamHealth as StreamHealth,
    )
    from decod_rs.io import (
        LogInfo as LogInfo,
    )
    from decod_rs.io import (
        ScanReader as ScanReader,
    )
    from decod_rs.io import (
        ScanRecord as ScanRecord,
    )
    from decod_rs.io import (
        TopicCheck as TopicCheck,
    )
    from decod_rs.io import (
        TopicInfo as TopicInfo,
    )
    from decod_rs.io import (
        check_log as check_log,
    )
    from decod_rs.io import (
        find_imu_topic as find_imu_topic,
    )
    from decod_rs.io import (
        inspect_log as inspect_log,
    )
    from decod_rs.io import (
        read_log as read_log,
    )
    from decod_rs.matching import (
        LandmarkDatabase as LandmarkDatabase,
    )
    from decod_rs.matching import (
        PairResult as PairResult,
    )
    from decod_rs.matching import (
        QueryResult as QueryResult,
    )
    from decod_rs.matching import (
        compare as compare,
    )
    from decod_rs.matching import (
        synthetic_landmark as synthetic_landmark,
    )
    from decod_rs.run_files import (
        LandmarkTable as LandmarkTable,
    )
    from decod_rs.run_files import (
        LoopTable as LoopTable,
    )
    from decod_rs.run_files import (
        loops_to_constraints as loops_to_constraints,
    )
    from decod_rs.run_files import (
        read_landmarks_csv as read_landmarks_csv,
    )
    from decod_rs.run_files import (
        read_loops_csv as read_loops_csv,
    )
    from decod_rs.run_files import (
        write_landmarks_csv as write_landmarks_csv,
    )
    from decod_rs.run_files import (
        write_loops_csv as write_loops_csv,
    )
    from decod_rs.tum import (
        interpolate_poses as interpolate_poses,
    )
    from decod_rs.tum import (
        read_tum as read_tum,
    )
    from decod_rs.tum import (
        write_tum as write_tum,
    )

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
    *_LAZY,
]


def __getattr__(name: str) -> Any:
    module = _LAZY.get(name)
    if module is None:
        raise AttributeError(f"module 'decod_rs' has no attribute {name!r}")
    value = getattr(importlib.import_module(module), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted([*globals(), *_LAZY])
