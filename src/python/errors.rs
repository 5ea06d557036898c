//! The one mapping from [`DecodError`] to Python exception types. Types are kept: a missing
//! file is `FileNotFoundError`, a malformed log is `LogFormatError` (a `ValueError`), etc.

use pyo3::exceptions::{PyException, PyLookupError, PyOSError, PyValueError};
use pyo3::prelude::*;

use crate::error::DecodError;

pyo3::create_exception!(
    _core,
    ConfigError,
    PyValueError,
    "A configuration value is invalid or unknown."
);
pyo3::create_exception!(
    _core,
    LogFormatError,
    PyValueError,
    "A log is malformed, truncated or corrupt."
);
pyo3::create_exception!(
    _core,
    UnsupportedMessageError,
    LogFormatError,
    "A message type or encoding decod cannot decode."
);
pyo3::create_exception!(
    _core,
    TopicError,
    PyLookupError,
    "A requested topic is missing or ambiguous; the message lists candidates."
);
pyo3::create_exception!(
    _core,
    DatabaseError,
    PyValueError,
    "A landmark database file has another format version or is corrupt."
);
pyo3::create_exception!(
    _core,
    InternalError,
    PyException,
    "A bug in decod: please report it with the input that caused it."
);

/// Converts a core error into the matching Python exception.
pub(crate) fn to_py_err(err: DecodError) -> PyErr {
    let message = err.to_string();
    match err {
        DecodError::InvalidInput { .. } => PyValueError::new_err(message),
        DecodError::Config { .. } => ConfigError::new_err(message),
        DecodError::Io { path, source } => {
            let errno = source.raw_os_error().unwrap_or(0);
            let args = (errno, source.to_string(), path.display().to_string());
            match source.kind() {
                std::io::ErrorKind::NotFound => {
                    pyo3::exceptions::PyFileNotFoundError::new_err(args)
                }
                std::io::ErrorKind::PermissionDenied => {
                    pyo3::exceptions::PyPermissionError::new_err(args)
                }
                _ => PyOSError::new_err(args),
            }
        }
        DecodError::Log { .. } => LogFormatError::new_err(message),
        DecodError::Topic { .. } => TopicError::new_err(message),
        DecodError::Unsupported { .. } => UnsupportedMessageError::new_err(message),
        DecodError::Database { .. } => DatabaseError::new_err(message),
    }
}

/// Registers the exception types on the module.
pub(crate) fn register(m: &Bound<'_, PyModule>) -> PyResult<()> {
    let py = m.py();
    m.add("ConfigError", py.get_type::<ConfigError>())?;
    m.add("LogFormatError", py.get_type::<LogFormatError>())?;
    m.add(
        "UnsupportedMessageError",
        py.get_type::<UnsupportedMessageError>(),
    )?;
    m.add("TopicError", py.get_type::<TopicError>())?;
    m.add("DatabaseError", py.get_type::<DatabaseError>())?;
    m.add("InternalError", py.get_type::<InternalError>())?;
    Ok(())
}
