//! Bindings for the extraction layer: submaps (built from scans and poses, or from a cloud
//! already in one frame), the streaming `SubmapBuilder`, and `extract_submap(s)` with their
//! typed results. Inputs are copied into owned Rust data, then the work runs in [`detached`].

use std::sync::Arc;

use numpy::{PyArray1, PyArray2, PyReadonlyArray1, PyReadonlyArray2, PyReadonlyArray3};
use pyo3::exceptions::PyValueError;
use pyo3::prelude::*;

use crate::config::DecodConfig;
use crate::extract::{
    ExtractionOutcome, Rejection, SubmapDiagnostics, extract_all, extract_landmarks,
};
use crate::geometry::{pose_from_matrix, pose_to_matrix};
use crate::scan::Scan;
use crate::submap::{Submap, SubmapBuilder};

use super::arrays::{flat_to_numpy, matrix_4x4, points_n3, vec3, vector};
use super::detached;
use super::errors::{ConfigError, to_py_err};
use super::landmark::PyLandmark;

/// Parses and validates a config given as JSON (what `decod_rs.Config.to_dict()` dumps).
pub(crate) fn config_from_json(json: &str) -> PyResult<DecodConfig> {
    let cfg: DecodConfig = serde_json::from_str(json)
        .map_err(|e| ConfigError::new_err(format!("invalid config JSON: {e}")))?;
    cfg.validate().map_err(to_py_err)?;
    Ok(cfg)
}

fn to_f32(points: Vec<[f64; 3]>) -> Vec<[f32; 3]> {
    points
        .into_iter()
        .map(|p| [p[0] as f32, p[1] as f32, p[2] as f32])
        .collect()
}

/// `(N, 3)` points that must be non-empty and finite; errors name `name` and the row.
fn checked_points(array: &PyReadonlyArray2<'_, f64>, name: &str) -> PyResult<Vec<[f32; 3]>> {
    let rows = points_n3(array, name)?;
    if rows.is_empty() {
        return Err(PyValueError::new_err(format!(
            "`{name}` is empty: expected shape (N, 3) with N >= 1"
        )));
    }
    if let Some(i) = rows.iter().position(|p| p.iter().any(|v| !v.is_finite())) {
        return Err(PyValueError::new_err(format!(
            "`{name}` row {i} is not finite: {:?}",
            rows[i]
        )));
    }
    Ok(to_f32(rows))
}

/// Scans accumulated into an anchor frame (see `decod::submap::Submap`).
#[pyclass(name = "Submap", module = "decod_rs._core", frozen)]
pub(crate) struct PySubmap {
    inner: Arc<Submap>,
}

#[pymethods]
impl PySubmap {
    /// Stamp of the anchor scan, seconds.
    #[getter]
    fn anchor_stamp(&self) -> f64 {
        self.inner.anchor_stamp
    }
    /// Stamps of the accumulated scans, `(K,)`.
    #[getter]
    fn scan_stamps<'py>(&self, py: Python<'py>) -> Bound<'py, PyArray1<f64>> {
        PyArray1::from_slice(py, &self.inner.scan_stamps)
    }
    /// `T_world_anchor`, `(4, 4)`.
    #[getter]
    fn world_from_anchor<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyArray2<f64>>> {
        flat_to_numpy(
            py,
            pose_to_matrix(&self.inner.world_from_anchor).to_vec(),
            4,
            4,
        )
    }
    /// Voxel-filtered points in the anchor frame, `(M, 3)` metres.
    #[getter]
    fn points<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyArray2<f64>>> {
        let flat: Vec<f64> = self
            .inner
            .points_in_anchor
            .iter()
            .flat_map(|p| p.map(f64::from))
            .collect();
        flat_to_numpy(py, flat, self.inner.points_in_anchor.len(), 3)
    }
    /// Unit gravity direction (down) in the anchor frame, `(3,)`.
    #[getter]
    fn gravity<'py>(&self, py: Python<'py>) -> Bound<'py, PyArray1<f64>> {
        PyArray1::from_slice(py, &self.inner.gravity_in_anchor)
    }
    /// Unit forward direction in the anchor frame, `(3,)`.
    #[getter]
    fn forward<'py>(&self, py: Python<'py>) -> Bound<'py, PyArray1<f64>> {
        PyArray1::from_slice(py, &self.inner.forward_in_anchor)
    }
    fn __len__(&self) -> usize {
        self.inner.points_in_anchor.len()
    }
    fn __repr__(&self) -> String {
        format!(
            "Submap(anchor_stamp={:.3}, scans={}, points={})",
            self.inner.anchor_stamp,
            self.inner.scan_stamps.len(),
            self.inner.points_in_anchor.len()
        )
    }
}

/// A submap or boundary that yielded no landmark, and why.
#[pyclass(name = "Rejection", module = "decod_rs._core", frozen)]
pub(crate) struct PyRejection {
    inner: Rejection,
}

#[pymethods]
impl PyRejection {
    /// Anchor stamp of the submap, seconds.
    #[getter]
    fn submap_stamp(&self) -> f64 {
        self.inner.submap_stamp
    }
    /// Machine-readable reason: `too_few_points`, `not_elongated`, `gravity_along_axis`,
    /// `contour_misfit`, `no_boundary`, `empty_descriptor`, `degenerate`.
    #[getter]
    fn kind(&self) -> &'static str {
        self.inner.reason.kind()
    }
    /// Human-readable explanation with the measured value and the threshold.
    #[getter]
    fn message(&self) -> String {
        self.inner.reason.to_string()
    }
    fn __str__(&self) -> String {
        self.inner.to_string()
    }
    fn __repr__(&self) -> String {
        format!(
            "Rejection({:?}, {:?})",
            self.inner.reason.kind(),
            self.inner.to_string()
        )
    }
}

/// What extraction measured in one submap.
#[pyclass(name = "SubmapDiagnostics", module = "decod_rs._core", frozen, get_all)]
pub(crate) struct PyDiagnostics {
    /// Points in the submap.
    point_count: usize,
    /// Corridor axis `(x, y, z)` in the submap frame.
    axis: (f64, f64, f64),
    /// Submap centroid, metres.
    centroid: (f64, f64, f64),
    /// Ratio of the two largest singular values.
    elongation: f64,
    /// `"circle"`, `"polar"` or `""` if not reached.
    contour_model: String,
    /// Contour centre along (e1, e2) from the centroid, metres.
    contour_centre_e1e2: (f64, f64),
    /// Mean contour radius, metres.
    contour_radius_m: f64,
    /// Fraction of projected points near the contour.
    contour_inlier_fraction: f64,
    /// Median |offset| from the contour, metres.
    contour_median_abs_offset_m: f64,
    /// 90th percentile of |offset| from the contour (the wall's relief), metres.
    contour_p90_abs_offset_m: f64,
    /// Radius of the corridor's curve within the submap, metres (inf: straight).
    curve_radius_m: f64,
    /// DoG maxima above threshold before NMS.
    boundary_candidates: usize,
    /// Robust spread of the DoG profile, metres.
    dog_sigma_m: f64,
    /// Peak threshold applied, metres.
    dog_threshold_m: f64,
    /// The cloud was cut before an end face in view (a tunnel's end, a pipe's cap): the
    /// figures above are the part before it.
    end_face: bool,
    /// The foot of the sensor on an end face in view (a tunnel's end, a pipe's cap), anchor
    /// frame, metres; None when the submap sees none.
    face_point: Option<(f64, f64, f64)>,
    /// That face's unit normal, anchor frame, oriented like `axis`.
    face_normal: Option<(f64, f64, f64)>,
}

impl From<&SubmapDiagnostics> for PyDiagnostics {
    fn from(d: &SubmapDiagnostics) -> Self {
        Self {
            point_count: d.point_count,
            axis: (d.axis[0], d.axis[1], d.axis[2]),
            centroid: (d.centroid[0], d.centroid[1], d.centroid[2]),
            elongation: d.elongation,
            contour_model: d.contour_model.clone(),
            contour_centre_e1e2: (d.contour_centre_e1e2[0], d.contour_centre_e1e2[1]),
            contour_radius_m: d.contour_radius_m,
            contour_inlier_fraction: d.contour_inlier_fraction,
            contour_median_abs_offset_m: d.contour_median_abs_offset_m,
            contour_p90_abs_offset_m: d.contour_p90_abs_offset_m,
            curve_radius_m: d.curve_radius_m,
            boundary_candidates: d.boundary_candidates,
            dog_sigma_m: d.dog_sigma_m,
            dog_threshold_m: d.dog_threshold_m,
            end_face: d.end_face,
            face_point: d.face_in_view.map(|f| f.point.into()),
            face_normal: d.face_in_view.map(|f| f.normal.into()),
        }
    }
}

/// Landmarks, rejections and diagnostics of one submap.
#[pyclass(name = "ExtractionResult", module = "decod_rs._core", frozen)]
pub(crate) struct PyExtractionResult {
    pub(crate) inner: ExtractionOutcome,
}

#[pymethods]
impl PyExtractionResult {
    /// One landmark per accepted boundary, strongest first.
    #[getter]
    fn landmarks(&self) -> Vec<PyLandmark> {
        self.inner
            .landmarks
            .iter()
            .map(|l| PyLandmark::new(l.clone()))
            .collect()
    }
    /// Every reason something yielded no landmark.
    #[getter]
    fn rejections(&self) -> Vec<PyRejection> {
        self.inner
            .rejections
            .iter()
            .map(|r| PyRejection { inner: r.clone() })
            .collect()
    }
    /// What the pipeline measured.
    #[getter]
    fn diagnostics(&self) -> PyDiagnostics {
        PyDiagnostics::from(&self.inner.diagnostics)
    }
    fn __repr__(&self) -> String {
        format!(
            "ExtractionResult(landmarks={}, rejections={:?})",
            self.inner.landmarks.len(),
            self.inner
                .rejections
                .iter()
                .map(|r| r.reason.kind())
                .collect::<Vec<_>>()
        )
    }
}

/// A submap from points already in one frame.
#[pyfunction]
#[pyo3(signature = (points, stamp, gravity, forward))]
fn submap_from_points(
    py: Python<'_>,
    points: PyReadonlyArray2<'_, f64>,
    stamp: f64,
    gravity: PyReadonlyArray1<'_, f64>,
    forward: PyReadonlyArray1<'_, f64>,
) -> PyResult<PySubmap> {
    let points = checked_points(&points, "points")?;
    let (gravity, forward) = (vec3(&gravity, "gravity")?, vec3(&forward, "forward")?);
    let submap = detached(py, move || {
        Submap::from_points(stamp, points, gravity, forward)
    })?;
    Ok(PySubmap {
        inner: Arc::new(submap),
    })
}

/// Accumulates scans with their poses into the frame of `scans[anchor_index]`.
#[pyfunction]
#[pyo3(signature = (stamps, points, poses, anchor_index, specific_force, config_json))]
fn build_submap(
    py: Python<'_>,
    stamps: PyReadonlyArray1<'_, f64>,
    points: Vec<PyReadonlyArray2<'_, f64>>,
    poses: PyReadonlyArray3<'_, f64>,
    anchor_index: usize,
    specific_force: Option<PyReadonlyArray2<'_, f64>>,
    config_json: &str,
) -> PyResult<PySubmap> {
    let cfg = config_from_json(config_json)?;
    let stamps = vector(&stamps);
    let k = stamps.len();
    let poses = poses.as_array();
    if poses.shape() != [k, 4, 4] {
        return Err(PyValueError::new_err(format!(
            "`poses` must have shape (K, 4, 4) with K = len(stamps) = {k}, got {:?}",
            poses.shape()
        )));
    }
    if points.len() != k {
        return Err(PyValueError::new_err(format!(
            "`points` must hold K = len(stamps) = {k} arrays, got {}",
            points.len()
        )));
    }
    let forces = match specific_force {
        Some(f) => {
            let rows = points_n3(&f, "specific_force")?;
            if rows.len() != k {
                return Err(PyValueError::new_err(format!(
                    "`specific_force` must have shape (K, 3) with K = {k}, got ({}, 3)",
                    rows.len()
                )));
            }
            rows.into_iter().map(Some).collect()
        }
        None => vec![None; k],
    };
    let mut scans = Vec::with_capacity(k);
    for (i, (cloud, force)) in points.iter().zip(forces).enumerate() {
        let mut m = [0.0; 16];
        for r in 0..4 {
            for c in 0..4 {
                m[r * 4 + c] = poses[[i, r, c]];
            }
        }
        scans.push(Scan {
            stamp: stamps[i],
            points_in_body: checked_points(cloud, &format!("points[{i}]"))?,
            world_from_body: pose_from_matrix(&m, &format!("poses[{i}]")).map_err(to_py_err)?,
            specific_force_in_body: force,
        });
    }
    let submap = detached(py, move || {
        Submap::from_scans(&scans, anchor_index, &cfg.submap)
    })?;
    Ok(PySubmap {
        inner: Arc::new(submap),
    })
}

/// Runs the extraction pipeline on one submap.
#[pyfunction]
fn extract_submap(
    py: Python<'_>,
    submap: &PySubmap,
    config_json: &str,
) -> PyResult<PyExtractionResult> {
    let cfg = config_from_json(config_json)?;
    let submap = Arc::clone(&submap.inner);
    let inner = detached(py, move || Ok(extract_landmarks(&submap, &cfg)))?;
    Ok(PyExtractionResult { inner })
}

/// Runs the extraction pipeline on many submaps in parallel (rayon), results in order.
#[pyfunction]
fn extract_submaps(
    py: Python<'_>,
    submaps: Vec<PyRef<'_, PySubmap>>,
    config_json: &str,
) -> PyResult<Vec<PyExtractionResult>> {
    let cfg = config_from_json(config_json)?;
    let owned: Vec<Submap> = submaps.iter().map(|m| (*m.inner).clone()).collect();
    let outcomes = detached(py, move || Ok(extract_all(&owned, &cfg)))?;
    Ok(outcomes
        .into_iter()
        .map(|inner| PyExtractionResult { inner })
        .collect())
}

/// Streams scans into submaps on the configured schedule (see `decod::submap::SubmapBuilder`).
#[pyclass(name = "SubmapBuilder", module = "decod_rs._core")]
pub(crate) struct PySubmapBuilder {
    inner: SubmapBuilder,
}

#[pymethods]
impl PySubmapBuilder {
    #[new]
    fn py_new(config_json: &str) -> PyResult<Self> {
        let cfg = config_from_json(config_json)?;
        Ok(Self {
            inner: SubmapBuilder::new(&cfg.submap),
        })
    }

    /// Adds one scan (`points` `(N, 3)` in the body frame, `pose` `(4, 4)` world_from_body);
    /// returns a submap when the scan completes a window.
    #[pyo3(signature = (stamp, points, pose, specific_force = None))]
    fn push(
        &mut self,
        py: Python<'_>,
        stamp: f64,
        points: PyReadonlyArray2<'_, f64>,
        pose: PyReadonlyArray2<'_, f64>,
        specific_force: Option<PyReadonlyArray1<'_, f64>>,
    ) -> PyResult<Option<PySubmap>> {
        let scan = Scan {
            stamp,
            points_in_body: to_f32(points_n3(&points, "points")?),
            world_from_body: pose_from_matrix(&matrix_4x4(&pose, "pose")?, "pose")
                .map_err(to_py_err)?,
            specific_force_in_body: specific_force
                .map(|f| vec3(&f, "specific_force"))
                .transpose()?,
        };
        let builder = &mut self.inner;
        let out = detached(py, move || builder.push(scan))?;
        Ok(out.map(|m| PySubmap { inner: Arc::new(m) }))
    }

    /// Emits the partial window left at the end of the stream, if any.
    fn finish(&mut self) -> PyResult<Option<PySubmap>> {
        let out = self.inner.finish().map_err(to_py_err)?;
        Ok(out.map(|m| PySubmap { inner: Arc::new(m) }))
    }
}

pub(crate) fn register(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_class::<PySubmap>()?;
    m.add_class::<PyRejection>()?;
    m.add_class::<PyDiagnostics>()?;
    m.add_class::<PyExtractionResult>()?;
    m.add_class::<PySubmapBuilder>()?;
    m.add_function(wrap_pyfunction!(submap_from_points, m)?)?;
    m.add_function(wrap_pyfunction!(build_submap, m)?)?;
    m.add_function(wrap_pyfunction!(extract_submap, m)?)?;
    m.add_function(wrap_pyfunction!(extract_submaps, m)?)?;
    Ok(())
}
