//! The private native module `decod_rs._core`: thin, shape-checked wrappers over the core.
//! Every heavy call converts its inputs to owned Rust data and runs through [`detached`],
//! which releases the GIL and maps errors once.

use pyo3::prelude::*;

mod arrays;
mod config;
mod errors;
mod extraction;
mod factor;
mod io;
mod landmark;
mod map_quality;
mod matching;
mod pipeline;
mod survey;

/// Runs `work` with the GIL released and maps a core error to its Python exception.
/// A Rust panic would already be a bug; catching it here keeps it from killing the
/// interpreter and reports it as `InternalError`.
pub(crate) fn detached<T, F>(py: Python<'_>, work: F) -> PyResult<T>
where
    F: FnOnce() -> crate::Result<T> + Send,
    T: Send,
{
    let outcome = py.detach(|| std::panic::catch_unwind(std::panic::AssertUnwindSafe(work)));
    match outcome {
        Ok(result) => result.map_err(errors::to_py_err),
        Err(payload) => {
            let text = payload
                .downcast_ref::<&str>()
                .map(|s| (*s).to_string())
                .or_else(|| payload.downcast_ref::<String>().cloned())
                .unwrap_or_else(|| "unknown panic".to_string());
            Err(errors::InternalError::new_err(text))
        }
    }
}

#[pymodule]
fn _core(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add("__version__", env!("CARGO_PKG_VERSION"))?;
    errors::register(m)?;
    config::register(m)?;
    landmark::register(m)?;
    map_quality::register(m)?;
    extraction::register(m)?;
    factor::register(m)?;
    io::register(m)?;
    matching::register(m)?;
    pipeline::register(m)?;
    survey::register(m)?;
    Ok(())
}
