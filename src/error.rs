//! One error type for the whole core. Bindings map each variant to a Python exception
//! type once (`src/python/errors.rs`); algorithm code never sees pyo3.

use std::path::PathBuf;

/// Every way decod can fail on its input. Messages name the file, topic or parameter at
/// fault so that a user can act on them without reading the source.
#[derive(Debug, thiserror::Error)]
pub enum DecodError {
    /// An argument has the wrong shape, a non-finite value, or is otherwise unusable.
    #[error("invalid input `{what}`: {reason}")]
    InvalidInput {
        /// The argument or field at fault (e.g. `points`, `poses[3]`).
        what: String,
        /// Why it is unusable.
        reason: String,
    },
    /// A configuration value is out of range or unknown.
    #[error("invalid config `{parameter}`: {reason}")]
    Config {
        /// Dotted path of the parameter, e.g. `boundary.nms_radius_m`.
        parameter: String,
        /// Why it is invalid.
        reason: String,
    },
    /// The operating system refused a file operation.
    #[error("{path}: {source}")]
    Io {
        /// The file concerned.
        path: PathBuf,
        /// The underlying error (kind is kept: NotFound stays NotFound in Python).
        #[source]
        source: std::io::Error,
    },
    /// A log (MCAP / rosbag2) is malformed, truncated or holds something we cannot decode.
    #[error("{path}{}: {reason}", topic.as_ref().map(|t| format!(" [topic {t}]")).unwrap_or_default())]
    Log {
        /// The log file.
        path: PathBuf,
        /// The topic concerned, when there is one.
        topic: Option<String>,
        /// What is wrong.
        reason: String,
    },
    /// A requested topic is missing or ambiguous; `candidates` lists what the log has.
    #[error("{path}: {reason}; candidates: [{}]", candidates.join(", "))]
    Topic {
        /// The log file.
        path: PathBuf,
        /// What was asked for and why it failed.
        reason: String,
        /// Topics of a suitable type (or all topics) present in the log.
        candidates: Vec<String>,
    },
    /// A message type or encoding decod does not decode.
    #[error("{path} [topic {topic}]: unsupported {reason}")]
    Unsupported {
        /// The log file.
        path: PathBuf,
        /// The topic concerned.
        topic: String,
        /// The type or encoding.
        reason: String,
    },
    /// A saved landmark database has another format version or is corrupt.
    #[error("{path}: {reason}")]
    Database {
        /// The database file.
        path: PathBuf,
        /// What is wrong.
        reason: String,
    },
}

/// Result alias used throughout the core.
pub type Result<T, E = DecodError> = std::result::Result<T, E>;

impl DecodError {
    /// Shorthand for [`DecodError::InvalidInput`].
    pub fn invalid(what: impl Into<String>, reason: impl Into<String>) -> Self {
        Self::InvalidInput {
            what: what.into(),
            reason: reason.into(),
        }
    }

    /// Shorthand for [`DecodError::Config`].
    pub fn config(parameter: impl Into<String>, reason: impl Into<String>) -> Self {
        Self::Config {
            parameter: parameter.into(),
            reason: reason.into(),
        }
    }
}
