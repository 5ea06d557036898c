//! `LogProcessor`: the log -> landmarks stream of `decod run`, one `step()` per batch of
//! submaps so Python can show progress between steps; the work runs with the GIL released.

use std::path::PathBuf;
use std::sync::Mutex;

use numpy::{PyArray1, PyArray2, PyArray3};
use pyo3::exceptions::PyValueError;
use pyo3::prelude::*;

use crate::geometry::pose_to_matrix;
use crate::io::{OdometrySource, ScanStreamOptions};
use crate::pipeline::{LogProcessor, ProcessedSubmap};

use super::arrays::flat_to_numpy;
use super::detached;
use super::extraction::{PyExtractionResult, config_from_json};

/// One processed submap: where it is and what extraction found in it.
#[pyclass(name = "ProcessedSubmap", module = "decod_rs._core", frozen)]
struct PyProcessedSubmap {
    #[pyo3(get)]
    anchor_stamp: f64,
    #[pyo3(get)]
    point_count: usize,
    pose: [f64; 16],
    scan_stamps: Vec<f64>,
    result: Py<PyExtractionResult>,
}

#[pymethods]
impl PyProcessedSubmap {
    /// Odometry pose of the anchor scan, `(4, 4)` world_from_anchor.
    #[getter]
    fn world_from_anchor<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyArray2<f64>>> {
        flat_to_numpy(py, self.pose.to_vec(), 4, 4)
    }
    /// Stamps of the scans accumulated, `(K,)`.
    #[getter]
    fn scan_stamps<'py>(&self, py: Python<'py>) -> Bound<'py, PyArray1<f64>> {
        PyArray1::from_slice(py, &self.scan_stamps)
    }
    /// Landmarks, rejections and diagnostics.
    #[getter]
    fn result(&self, py: Python<'_>) -> Py<PyExtractionResult> {
        self.result.clone_ref(py)
    }
}

/// Streams a log through submaps and extraction (see `decod::pipeline::LogProcessor`).
#[pyclass(name = "LogProcessor", module = "decod_rs._core")]
struct PyLogProcessor {
    // The MCAP decompressors are Send but not Sync; the lock makes the class shareable.
    inner: Mutex<LogProcessor>,
}

impl PyLogProcessor {
    fn lock(&self) -> PyResult<std::sync::MutexGuard<'_, LogProcessor>> {
        self.inner
            .lock()
            .map_err(|_| PyValueError::new_err("LogProcessor is poisoned by an earlier panic"))
    }
}

#[pymethods]
impl PyLogProcessor {
    #[new]
    #[pyo3(signature = (path, config_json, *, points_topic = None, odom_topic = None, odom_tum = None, imu_topic = None, batch = 2))]
    #[allow(clippy::too_many_arguments)]
    fn py_new(
        py: Python<'_>,
        path: PathBuf,
        config_json: &str,
        points_topic: Option<String>,
        odom_topic: Option<String>,
        odom_tum: Option<PathBuf>,
        imu_topic: Option<String>,
        batch: usize,
    ) -> PyResult<Self> {
        if odom_topic.is_some() && odom_tum.is_some() {
            return Err(PyValueError::new_err(
                "give either odom_topic or odom_tum, not both",
            ));
        }
        let config = config_from_json(config_json)?;
        let options = ScanStreamOptions {
            points_topic,
            odometry: match odom_tum {
                Some(tum) => OdometrySource::Tum(tum),
                None => OdometrySource::Topic(odom_topic),
            },
            imu_topic,
        };
        let inner = detached(py, || LogProcessor::open(&path, &options, &config, batch))?;
        Ok(Self {
            inner: Mutex::new(inner),
        })
    }

    /// The next batch of processed submaps, or `None` at the end of the log.
    fn step(&mut self, py: Python<'_>) -> PyResult<Option<Vec<PyProcessedSubmap>>> {
        let mut guard = self.lock()?;
        let inner = &mut *guard;
        let batch: Option<Vec<ProcessedSubmap>> = detached(py, || inner.step())?;
        let Some(batch) = batch else {
            return Ok(None);
        };
        batch
            .into_iter()
            .map(|(record, outcome)| {
                Ok(PyProcessedSubmap {
                    anchor_stamp: record.anchor_stamp,
                    point_count: record.point_count,
                    pose: pose_to_matrix(&record.world_from_anchor),
                    scan_stamps: record.scan_stamps,
                    result: Py::new(py, PyExtractionResult { inner: outcome })?,
                })
            })
            .collect::<PyResult<Vec<_>>>()
            .map(Some)
    }

    /// Scans read so far.
    #[getter]
    fn scans_read(&self) -> PyResult<usize> {
        Ok(self.lock()?.scan_stamps().len())
    }
    /// Point-cloud messages in the log (0 if unknown).
    #[getter]
    fn total_scans_hint(&self) -> PyResult<u64> {
        Ok(self.lock()?.total_scans_hint())
    }
    /// The point-cloud topic being read.
    #[getter]
    fn points_topic(&self) -> PyResult<String> {
        Ok(self.lock()?.points_topic().to_string())
    }
    /// Stamps of scans skipped because they lie outside the odometry span.
    #[getter]
    fn skipped_outside_odometry(&self) -> PyResult<Vec<f64>> {
        Ok(self.lock()?.skipped_outside_odometry().to_vec())
    }
    /// Stamps of every scan read so far, `(M,)`.
    fn scan_stamps<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyArray1<f64>>> {
        Ok(PyArray1::from_slice(py, self.lock()?.scan_stamps()))
    }
    /// Odometry pose of every scan read so far, `(M, 4, 4)` world_from_body.
    fn scan_poses<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyArray3<f64>>> {
        let guard = self.lock()?;
        let poses = guard.scan_poses();
        let flat: Vec<f64> = poses.iter().flat_map(pose_to_matrix).collect();
        numpy::ndarray::Array3::from_shape_vec((poses.len(), 4, 4), flat)
            .map(|a| numpy::IntoPyArray::into_pyarray(a, py))
            .map_err(|e| PyValueError::new_err(format!("internal shape error: {e}")))
    }
}

pub(crate) fn register(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_class::<PyLogProcessor>()?;
    m.add_class::<PyProcessedSubmap>()?;
    Ok(())
}
