//! `LogProcessor`: the log -> landmarks stream of `decod run`, one `step()` per batch of
//! submaps so Python can show progress between steps; the work runs with the GIL released.
//! After the stream, the run's voxel map (`decod::map::SegmentMap`) is rendered by any
//! trajectory (`render_map`) for the corrected and odometry point clouds.

use std::path::PathBuf;
use std::sync::Mutex;

use numpy::{PyArray1, PyArray2, PyArray3, PyReadonlyArray1, PyReadonlyArray2, PyReadonlyArray3};
use pyo3::exceptions::PyValueError;
use pyo3::prelude::*;

use crate::geometry::{Pose, pose_from_matrix, pose_to_matrix};
use crate::io::imu::ImuSample;
use crate::io::{OdometrySource, ScanStreamOptions};
use crate::map::SegmentMap;
use crate::pipeline::{LogProcessor, ProcessedSubmap};

use super::arrays::{flat_to_numpy, imu_to_numpy, rows_n};
use super::detached;
use super::errors::to_py_err;
use super::extraction::{PyExtractionResult, config_from_json};
use super::io::{HealthRow, health_of};

/// One processed submap: where it is and what extraction found in it.
#[pyclass(name = "ProcessedSubmap", module = "decod_rs._core", frozen)]
struct PyProcessedSubmap {
    #[pyo3(get)]
    anchor_stamp: f64,
    #[pyo3(get)]
    point_count: usize,
    pose: [f64; 16],
    scan_stamps: Vec<f64>,
    points: Vec<[f32; 3]>,
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
    /// Voxel-filtered points in the anchor frame, `(N, 3)` float32, metres.
    #[getter]
    fn points_in_anchor<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyArray2<f32>>> {
        let flat: Vec<f32> = self.points.iter().flatten().copied().collect();
        flat_to_numpy(py, flat, self.points.len(), 3)
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
    #[pyo3(signature = (path, config_json, *, points_topic = None, odom_topic = None, odom_tum = None, imu_topic = None, batch = 2, map = true, imu_samples = None))]
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
        map: bool,
        imu_samples: Option<PyReadonlyArray2<'_, f64>>,
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
            imu_samples: imu_samples.map(|a| imu_rows(&a)).transpose()?,
            gap_periods: config.submap.odometry_gap_periods,
            deskew: config.submap.deskew,
        };
        let mut inner = detached(py, || LogProcessor::open(&path, &options, &config, batch))?;
        if !map {
            inner = inner.without_map();
        }
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
                    points: record.points_in_anchor,
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
    /// Windows `submap.max_travel_m` closed so far (the robot faster than the schedule's
    /// speed).
    #[getter]
    fn windows_closed_by_travel(&self) -> PyResult<usize> {
        Ok(self.lock()?.windows_closed_by_travel())
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
    /// What the stream met: faults, odometry gaps, clouds left out (`_ScanReader.health`).
    fn health(&self) -> PyResult<HealthRow> {
        Ok(health_of(self.lock()?.stream()))
    }
    /// Stamps of scans skipped because they lie outside the odometry span.
    #[getter]
    fn skipped_outside_odometry(&self) -> PyResult<Vec<f64>> {
        Ok(self.lock()?.skipped_outside_odometry().to_vec())
    }
    /// The IMU samples attached to scans, `(N, 4)`: stamp (s) and specific force (m/s^2),
    /// sorted by stamp; `None` without an IMU. Give them to a later processor of the same log
    /// (`imu_samples=`) to spare it a pass over the file.
    fn imu_samples<'py>(&self, py: Python<'py>) -> PyResult<Option<Bound<'py, PyArray2<f64>>>> {
        imu_to_numpy(py, self.lock()?.stream().imu())
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
    /// Map voxel edge, metres (None when the map is disabled).
    #[getter]
    fn map_voxel_m(&self) -> PyResult<Option<f64>> {
        Ok(self.lock()?.map().map(SegmentMap::voxel_m))
    }
    /// Travel per map segment, metres (None when the map is disabled).
    #[getter]
    fn map_segment_length_m(&self) -> PyResult<Option<f64>> {
        Ok(self.lock()?.map().map(SegmentMap::segment_length_m))
    }
    /// Voxels the map holds in memory (0 when disabled).
    #[getter]
    fn map_stored_voxels(&self) -> PyResult<usize> {
        Ok(self.lock()?.map().map_or(0, SegmentMap::stored_voxels))
    }
    /// Segments of the map (0 when disabled).
    #[getter]
    fn map_segments(&self) -> PyResult<usize> {
        Ok(self.lock()?.map().map_or(0, SegmentMap::segment_count))
    }
    /// Anchor stamps of the map's submaps, `(K,)`: the order `render_map` wants poses in.
    fn map_submap_stamps<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyArray1<f64>>> {
        let guard = self.lock()?;
        Ok(PyArray1::from_slice(py, map_of(&guard)?.submap_stamps()))
    }
    /// The map placed by `world_from_submap` `(K, 4, 4)` (one pose per submap, e.g. the
    /// corrected poses at `map_submap_stamps()`), one point per `voxel_m` voxel and pass
    /// (`pass_of_submap` `(K,)` uint8). Returns `(points (N, 3) f64, pass (N,) u8,
    /// first_submap (N,) u32, count (N,) u32)`.
    #[pyo3(signature = (world_from_submap, pass_of_submap, voxel_m = None))]
    fn render_map<'py>(
        &self,
        py: Python<'py>,
        world_from_submap: PyReadonlyArray3<'_, f64>,
        pass_of_submap: PyReadonlyArray1<'_, u8>,
        voxel_m: Option<f64>,
    ) -> PyResult<RenderedMap<'py>> {
        let guard = self.lock()?;
        let map = map_of(&guard)?;
        let k = map.submap_stamps().len();
        let poses = poses_k44(&world_from_submap, k, "world_from_submap")?;
        let pass: Vec<u8> = pass_of_submap.as_array().iter().copied().collect();
        let voxel = voxel_m.unwrap_or_else(|| map.voxel_m());
        let cloud = detached(py, || map.render(&poses, &pass, voxel))?;
        let n = cloud.points.len();
        let flat: Vec<f64> = cloud.points.iter().flatten().copied().collect();
        Ok((
            flat_to_numpy(py, flat, n, 3)?,
            PyArray1::from_vec(py, cloud.pass),
            PyArray1::from_vec(py, cloud.first_submap),
            PyArray1::from_vec(py, cloud.count),
        ))
    }
    /// Every stored voxel in the anchor frame of the submap that first saw it, `(M, 3)`
    /// float32, and that submap's index `(M,)` uint32, sorted by submap.
    fn map_points_by_submap<'py>(&self, py: Python<'py>) -> PyResult<SubmapPoints<'py>> {
        let guard = self.lock()?;
        let map = map_of(&guard)?;
        let (points, submap) = detached(py, || Ok(map.points_by_submap()))?;
        let flat: Vec<f32> = points.iter().flatten().copied().collect();
        Ok((
            flat_to_numpy(py, flat, points.len(), 3)?,
            PyArray1::from_vec(py, submap),
        ))
    }
}

/// `(N, 4)` rows of stamp and specific force into IMU samples (non-finite rows are dropped
/// by the series, as when read from the log).
fn imu_rows(array: &PyReadonlyArray2<'_, f64>) -> PyResult<Vec<ImuSample>> {
    Ok(
        rows_n::<4>(array, "imu_samples (stamp, specific force x, y, z)")?
            .into_iter()
            .map(|[stamp, x, y, z]| ImuSample {
                stamp,
                specific_force: [x, y, z],
            })
            .collect(),
    )
}

/// The voxel map of a processor, or a ValueError when it was created with `map=False`.
fn map_of(processor: &LogProcessor) -> PyResult<&SegmentMap> {
    processor
        .map()
        .ok_or_else(|| PyValueError::new_err("this LogProcessor was created with map=False"))
}

/// `(K, 4, 4)` poses into owned poses, each checked (`name[i]` in errors).
fn poses_k44(array: &PyReadonlyArray3<'_, f64>, k: usize, name: &str) -> PyResult<Vec<Pose>> {
    let view = array.as_array();
    if view.shape() != [k, 4, 4] {
        return Err(PyValueError::new_err(format!(
            "`{name}` must have shape ({k}, 4, 4) (one pose per map submap), got {:?}",
            view.shape()
        )));
    }
    (0..k)
        .map(|i| {
            let mut m = [0.0; 16];
            for r in 0..4 {
                for c in 0..4 {
                    m[r * 4 + c] = view[[i, r, c]];
                }
            }
            pose_from_matrix(&m, &format!("{name}[{i}]")).map_err(to_py_err)
        })
        .collect()
}

/// What `map_points_by_submap` returns: points `(M, 3)` f32 and their submap `(M,)` u32.
type SubmapPoints<'py> = (Bound<'py, PyArray2<f32>>, Bound<'py, PyArray1<u32>>);

/// What `render_map` returns: points `(N, 3)` f64, pass `(N,)` u8, first submap `(N,)` u32,
/// merged points `(N,)` u32.
type RenderedMap<'py> = (
    Bound<'py, PyArray2<f64>>,
    Bound<'py, PyArray1<u8>>,
    Bound<'py, PyArray1<u32>>,
    Bound<'py, PyArray1<u32>>,
);

pub(crate) fn register(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_class::<PyLogProcessor>()?;
    m.add_class::<PyProcessedSubmap>()?;
    Ok(())
}
