//! Bindings for the io layer (issue 4): the scan stream as a Python iterator, log inspection
//! and TUM reading. Typed wrappers live in `python/decod_rs/io.py`.

use std::path::PathBuf;
use std::sync::Mutex;

use numpy::{PyArray1, PyArray2};
use pyo3::exceptions::PyValueError;
use pyo3::prelude::*;

use super::arrays::{flat_to_numpy, imu_to_numpy, rows_to_numpy};
use super::detached;
use crate::geometry::{pose_to_matrix, pose_to_tq};
use crate::io::{LogFault, OdometrySource, ScanStream, ScanStreamOptions};

/// One scan as `(stamp, points (N, 3) float32, world_from_body (4, 4) float64,
/// specific_force (3,) float64 or None)`.
type ScanTuple<'py> = (
    f64,
    Bound<'py, PyArray2<f32>>,
    Bound<'py, PyArray2<f64>>,
    Option<Bound<'py, PyArray1<f64>>>,
);

/// A streaming reader of scans (see `decod::io::ScanStream`). The stream sits behind a mutex
/// because pyclasses must be `Sync`; each `__next__` decodes one cloud with the GIL released.
#[pyclass(name = "_ScanReader", module = "decod_rs._core", frozen)]
struct ScanReader {
    stream: Mutex<ScanStream>,
}

fn lock(m: &Mutex<ScanStream>) -> std::sync::MutexGuard<'_, ScanStream> {
    m.lock().unwrap_or_else(std::sync::PoisonError::into_inner)
}

#[pymethods]
impl ScanReader {
    fn __iter__(slf: PyRef<'_, Self>) -> PyRef<'_, Self> {
        slf
    }

    fn __next__<'py>(&self, py: Python<'py>) -> PyResult<Option<ScanTuple<'py>>> {
        let next = detached(py, || lock(&self.stream).next().transpose())?;
        let Some(scan) = next else { return Ok(None) };
        let n = scan.points_in_body.len();
        let flat: Vec<f32> = scan.points_in_body.into_iter().flatten().collect();
        let points = flat_to_numpy(py, flat, n, 3)?;
        let pose = flat_to_numpy(py, pose_to_matrix(&scan.world_from_body).to_vec(), 4, 4)?;
        let force = scan
            .specific_force_in_body
            .map(|f| PyArray1::from_slice(py, &f));
        Ok(Some((scan.stamp, points, pose, force)))
    }

    /// Stamps of the clouds skipped so far (outside the odometry span).
    fn skipped_outside_odometry(&self) -> Vec<f64> {
        lock(&self.stream).skipped_outside_odometry().to_vec()
    }

    /// Cloud messages on the points topic (progress-bar total).
    fn total_scans_hint(&self) -> u64 {
        lock(&self.stream).total_scans_hint()
    }

    /// Points dropped so far because a coordinate was NaN or infinite.
    fn dropped_non_finite_points(&self) -> usize {
        lock(&self.stream).dropped_non_finite_points()
    }

    /// The point-cloud topic being read.
    fn points_topic(&self) -> String {
        lock(&self.stream).points_topic().to_string()
    }

    /// What the stream met so far: faults, gaps, clouds left out (see `health_of`).
    fn health(&self) -> HealthRow {
        health_of(&lock(&self.stream))
    }

    /// The IMU samples the first pass read, `(N, 4)`: stamp (s) and specific force
    /// (m/s^2), sorted by stamp; `None` without an IMU. A later processor of the same log
    /// takes them (`LogProcessor(imu_samples=)`) instead of reading the whole file again.
    fn imu_samples<'py>(&self, py: Python<'py>) -> PyResult<Option<Bound<'py, PyArray2<f64>>>> {
        imu_to_numpy(py, lock(&self.stream).imu())
    }

    /// The odometry as TUM rows `(N, 8)`: `stamp tx ty tz qx qy qz qw`.
    fn odometry<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyArray2<f64>>> {
        let rows: Vec<[f64; 8]> = lock(&self.stream)
            .odometry()
            .iter()
            .map(|(t, p)| tum_row(*t, p))
            .collect();
        rows_to_numpy(py, &rows)
    }
}

/// A `decod::io::LogFault` as `(file, kind, offset, reason, last_complete_s, lost_span_s,
/// messages_lost, message)`.
pub(crate) type FaultRow = (
    String,
    String,
    u64,
    String,
    Option<f64>,
    Option<(f64, f64)>,
    Option<u64>,
    String,
);

/// `(faults, odometry gaps (start, end, kind), stamps skipped in gaps, out-of-order clouds
/// (stamp, previous), cloud counts (messages, undecodable, zero_size, empty,
/// non_finite_points, out_of_order, deskewed, times_unused), message errors)` of a scan
/// stream.
pub(crate) type HealthRow = (
    Vec<FaultRow>,
    Vec<(f64, f64, String)>,
    Vec<f64>,
    Vec<(f64, f64)>,
    (u64, u64, u64, u64, u64, u64, u64, u64),
    Vec<String>,
);

pub(crate) fn fault_row(f: &LogFault) -> FaultRow {
    let secs = |ns: u64| ns as f64 * 1e-9;
    (
        f.file.display().to_string(),
        f.kind.name().to_string(),
        f.offset,
        f.reason.clone(),
        f.last_complete_ns.map(secs),
        f.lost_span_ns.map(|(a, b)| (secs(a), secs(b))),
        f.messages_lost,
        f.to_string(),
    )
}

pub(crate) fn health_of(stream: &ScanStream) -> HealthRow {
    let c = stream.cloud_stats();
    (
        stream.faults().iter().map(fault_row).collect(),
        stream
            .odometry_gaps()
            .iter()
            .map(|g| (g.start, g.end, g.kind.name().to_string()))
            .collect(),
        stream.skipped_in_gaps().to_vec(),
        stream.out_of_order().to_vec(),
        (
            c.messages,
            c.undecodable,
            c.zero_size,
            c.empty,
            c.non_finite_points,
            c.out_of_order,
            c.deskewed,
            c.times_unused,
        ),
        stream.message_errors().to_vec(),
    )
}

fn tum_row(stamp: f64, pose: &crate::geometry::Pose) -> [f64; 8] {
    let (t, q) = pose_to_tq(pose);
    [stamp, t[0], t[1], t[2], q[0], q[1], q[2], q[3]]
}

/// Opens a scan stream (reads odometry and IMU first). `odom` and `odom_tum` are exclusive.
#[pyfunction]
/// `gap_periods`: odometry gap bound in median periods (5.0 = `DEFAULT_GAP_PERIODS`);
/// `deskew`: points moved to the stamp's pose by their own times (`crate::deskew`).
#[pyo3(signature = (path, points = None, odom = None, odom_tum = None, imu = None, gap_periods = 5.0, deskew = true))]
#[allow(clippy::too_many_arguments)]
fn open_scan_stream(
    py: Python<'_>,
    path: PathBuf,
    points: Option<String>,
    odom: Option<String>,
    odom_tum: Option<PathBuf>,
    imu: Option<String>,
    gap_periods: f64,
    deskew: bool,
) -> PyResult<ScanReader> {
    let odometry = match (odom, odom_tum) {
        (Some(_), Some(_)) => {
            return Err(PyValueError::new_err(
                "give odometry as a topic (`odom`) or a TUM file (`odom_tum`), not both",
            ));
        }
        (None, Some(tum)) => OdometrySource::Tum(tum),
        (topic, None) => OdometrySource::Topic(topic),
    };
    let opts = ScanStreamOptions {
        points_topic: points,
        odometry,
        imu_topic: imu,
        imu_samples: None,
        gap_periods,
        deskew,
    };
    let stream = detached(py, || ScanStream::open(&path, &opts))?;
    Ok(ScanReader {
        stream: Mutex::new(stream),
    })
}

/// `(topic, type, encoding, count)` rows of a log.
type TopicRow = (String, String, String, u64);

/// `(files, topics, start, end, problem)` of a log.
type LogRow = (
    Vec<String>,
    Vec<TopicRow>,
    Option<f64>,
    Option<f64>,
    Option<String>,
);

/// `(files, topics, start, end, problem)` of a log.
#[pyfunction]
fn inspect_log(py: Python<'_>, path: PathBuf) -> PyResult<LogRow> {
    let s = detached(py, || crate::io::inspect(&path))?;
    Ok((
        s.files.iter().map(|f| f.display().to_string()).collect(),
        s.topics
            .into_iter()
            .map(|t| (t.topic, t.message_type, t.encoding, t.count))
            .collect(),
        s.start,
        s.end,
        s.problem,
    ))
}

/// `(topic, type, supported, messages, decoded, points, first_error)` of a verified topic.
type CheckRow = (String, String, bool, u64, u64, u64, Option<String>);

/// Reads and decodes every message (see `decod::io::check`).
#[pyfunction]
fn check_log(py: Python<'_>, path: PathBuf) -> PyResult<Vec<CheckRow>> {
    let topics = detached(py, || crate::io::check(&path))?;
    Ok(topics
        .into_iter()
        .map(|t| {
            let row = (t.topic, t.message_type, t.supported, t.messages);
            (
                row.0,
                row.1,
                row.2,
                row.3,
                t.decoded,
                t.points,
                t.first_error,
            )
        })
        .collect())
}

/// The unique sensor_msgs/Imu topic, None when there is none (TopicError when several).
#[pyfunction]
fn find_imu_topic(py: Python<'_>, path: PathBuf) -> PyResult<Option<String>> {
    detached(py, || crate::io::find_imu_topic(&path))
}

/// A TUM file as `(N, 8)` rows `stamp tx ty tz qx qy qz qw` (quaternions normalised).
#[pyfunction]
fn read_tum<'py>(py: Python<'py>, path: PathBuf) -> PyResult<Bound<'py, PyArray2<f64>>> {
    let poses = detached(py, || crate::io::read_tum(&path))?;
    let rows: Vec<[f64; 8]> = poses.iter().map(|(t, p)| tum_row(*t, p)).collect();
    rows_to_numpy(py, &rows)
}

pub(crate) fn register(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_class::<ScanReader>()?;
    m.add_function(wrap_pyfunction!(open_scan_stream, m)?)?;
    m.add_function(wrap_pyfunction!(inspect_log, m)?)?;
    m.add_function(wrap_pyfunction!(find_imu_topic, m)?)?;
    m.add_function(wrap_pyfunction!(check_log, m)?)?;
    m.add_function(wrap_pyfunction!(read_tum, m)?)?;
    Ok(())
}
