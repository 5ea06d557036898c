//! Bindings for the survey file (`decod::survey`): write and read, header as JSON text; and
//! for landmarks a run sets aside while it rebuilds (`decod::park`).

use std::path::PathBuf;
use std::sync::Arc;

use pyo3::prelude::*;

use super::detached;
use super::errors::to_py_err;
use super::landmark::{PyLandmark, PySpill, held_of};
use crate::error::DecodError;
use crate::park;
use crate::spill::Held;
use crate::survey::{self, FORMAT_VERSION, Survey};

/// Writes a survey: `header_json` (a JSON object with `joint_ids`, one per landmark) and the
/// landmarks, in the versioned binary format of `decod::survey`.
#[pyfunction]
fn write_survey(
    py: Python<'_>,
    path: PathBuf,
    header_json: &str,
    landmarks: Vec<PyRef<'_, PyLandmark>>,
) -> PyResult<()> {
    let header = serde_json::from_str(header_json)
        .map_err(|e| to_py_err(DecodError::invalid("header_json", e.to_string())))?;
    // The run's landmarks are shared with the writer, not copied (a long log's are 0.2 GB).
    let landmarks = held_of(&landmarks);
    detached(py, move || survey::write_survey(&path, &header, &landmarks))
}

/// Reads a survey: `(header_json, landmarks)`; `DatabaseError` for another format version,
/// a foreign, truncated or inconsistent file. With `spill`, each landmark's cells go there
/// as it is read (`Survey::read_into`): the landmarks hold their heads in memory.
#[pyfunction]
#[pyo3(signature = (path, spill = None))]
fn read_survey(
    py: Python<'_>,
    path: PathBuf,
    spill: Option<PyRef<'_, PySpill>>,
) -> PyResult<(String, Vec<PyLandmark>)> {
    let spill = spill.map(|s| Arc::clone(&s.inner));
    let (header, held) = detached(py, move || match spill {
        Some(spill) => Survey::read_into(&path, &spill),
        None => Survey::read(&path).map(|s| {
            let held = s.landmarks.into_iter().map(Held::from).collect();
            (s.header, held)
        }),
    })?;
    let header = serde_json::to_string(&header)
        .map_err(|e| to_py_err(DecodError::invalid("survey header", e.to_string())))?;
    Ok((
        header,
        held.into_iter().map(PyLandmark::from_held).collect(),
    ))
}

/// Sets `landmarks` aside in `path`, exactly (`decod::park`): a run's earlier round while it
/// rebuilds its submaps.
#[pyfunction]
fn park_landmarks(
    py: Python<'_>,
    path: PathBuf,
    landmarks: Vec<PyRef<'_, PyLandmark>>,
) -> PyResult<()> {
    let landmarks = held_of(&landmarks);
    detached(py, move || park::write(&path, &landmarks))
}

/// The landmarks [`park_landmarks`] set aside in `path`, in their order.
#[pyfunction]
fn unpark_landmarks(py: Python<'_>, path: PathBuf) -> PyResult<Vec<PyLandmark>> {
    let landmarks = detached(py, move || park::read(&path))?;
    Ok(landmarks.into_iter().map(PyLandmark::new).collect())
}

pub(crate) fn register(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add("SURVEY_FORMAT_VERSION", FORMAT_VERSION)?;
    m.add_function(wrap_pyfunction!(write_survey, m)?)?;
    m.add_function(wrap_pyfunction!(read_survey, m)?)?;
    m.add_function(wrap_pyfunction!(park_landmarks, m)?)?;
    m.add_function(wrap_pyfunction!(unpark_landmarks, m)?)?;
    Ok(())
}
