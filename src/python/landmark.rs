//! `decod_rs._core.Landmark`: one boundary with its descriptor, shared by the extraction and
//! matching bindings. Immutable; arrays come out as fresh numpy arrays. Its cells may wait on
//! disk (`decod::spill`, `Spill.put`): they are then read back each time they are asked for.

use std::path::PathBuf;
use std::sync::Arc;

use numpy::{PyArray1, PyArray2, PyReadonlyArray1, PyReadonlyArray2};
use pyo3::exceptions::PyValueError;
use pyo3::prelude::*;

use crate::landmark::{Descriptor, Landmark};
use crate::spill::{Held, Spill};

use super::arrays::{flat_to_numpy, rows_to_numpy, vec3, vector};
use super::detached;
use super::errors::to_py_err;

/// A detected cross-sectional boundary (see `decod::landmark::Landmark`), in memory or with
/// its cells on disk (`decod::spill::Held`).
#[pyclass(name = "Landmark", module = "decod_rs._core", frozen)]
pub(crate) struct PyLandmark {
    pub(crate) held: Held,
}

impl PyLandmark {
    /// Wraps a core landmark.
    pub(crate) fn new(inner: Landmark) -> Self {
        Self {
            held: Held::from(inner),
        }
    }

    /// Wraps a landmark in memory or on disk.
    pub(crate) fn from_held(held: Held) -> Self {
        Self { held }
    }

    /// The landmark's fields (its cells empty where they are on disk: `Held::head`).
    fn head(&self) -> &Landmark {
        self.held.head()
    }

    /// The whole landmark, read back where its cells are on disk.
    pub(crate) fn whole(&self) -> PyResult<Arc<Landmark>> {
        self.held.landmark().map_err(to_py_err)
    }
}

/// The landmarks held by `items` (shared, not copied; those on disk stay there).
pub(crate) fn held_of(items: &[PyRef<'_, PyLandmark>]) -> Vec<Held> {
    items.iter().map(|l| l.held.clone()).collect()
}

/// A file a run's landmarks wait in while their views are matched (`decod::spill`): created
/// in `directory` (on Unix unlinked at once: it leaves nothing behind), gone with the last
/// landmark put in it.
#[pyclass(name = "Spill", module = "decod_rs._core", frozen)]
pub(crate) struct PySpill {
    pub(crate) inner: Arc<Spill>,
}

#[pymethods]
impl PySpill {
    #[new]
    fn py_new(directory: PathBuf) -> PyResult<Self> {
        Ok(Self {
            inner: Spill::create(&directory).map_err(to_py_err)?,
        })
    }
    /// The landmarks with their cells written here, in their order: the same landmarks,
    /// holding a few hundred bytes each instead of about 29 KB. Those already on disk are
    /// given back as they are.
    fn put(
        &self,
        py: Python<'_>,
        landmarks: Vec<PyRef<'_, PyLandmark>>,
    ) -> PyResult<Vec<PyLandmark>> {
        let held = held_of(&landmarks);
        let spill = Arc::clone(&self.inner);
        let put = detached(py, move || {
            held.into_iter()
                .map(|h| match &h {
                    Held::Memory(l) => spill.put(l),
                    Held::Disk(_) => Ok(h),
                })
                .collect::<crate::Result<Vec<_>>>()
        })?;
        Ok(put.into_iter().map(PyLandmark::from_held).collect())
    }
    /// Bytes written so far.
    #[getter]
    fn bytes(&self) -> u64 {
        self.inner.bytes()
    }
}

/// The contour of a landmark given from Python, (cols, 2) in the section's `(e1, e2)` frame.
fn contour_points(contour: &PyReadonlyArray2<'_, f64>) -> PyResult<Vec<[f64; 2]>> {
    let c = contour.as_array();
    if c.ncols() != 2 {
        return Err(PyValueError::new_err(format!(
            "`contour` must have shape (cols, 2), got {:?}",
            c.shape()
        )));
    }
    Ok(c.rows().into_iter().map(|r| [r[0], r[1]]).collect())
}

#[pymethods]
impl PyLandmark {
    /// Builds a landmark from arrays (for descriptors computed elsewhere, and tests).
    /// `descriptor` and `mask` are `(rows, cols)` (the offsets kept in single precision, as
    /// `decod::landmark::Descriptor` holds them); `e1` must be perpendicular to `axis`.
    #[new]
    #[pyo3(signature = (
        submap_stamp, origin, axis, e1, descriptor, mask, *, cell_z_m, perimeter_m,
        normal_e1 = None, normal_e2 = None, contour = None, radius_m = 0.0, strength = 0.0,
        scan_stamps = None
    ))]
    #[allow(clippy::too_many_arguments)]
    fn py_new(
        submap_stamp: f64,
        origin: PyReadonlyArray1<'_, f64>,
        axis: PyReadonlyArray1<'_, f64>,
        e1: PyReadonlyArray1<'_, f64>,
        descriptor: PyReadonlyArray2<'_, f64>,
        mask: PyReadonlyArray2<'_, bool>,
        cell_z_m: f64,
        perimeter_m: f64,
        normal_e1: Option<PyReadonlyArray1<'_, f64>>,
        normal_e2: Option<PyReadonlyArray1<'_, f64>>,
        contour: Option<PyReadonlyArray2<'_, f64>>,
        radius_m: f64,
        strength: f64,
        scan_stamps: Option<PyReadonlyArray1<'_, f64>>,
    ) -> PyResult<Self> {
        let axis = vec3(&axis, "axis")?;
        let e1 = vec3(&e1, "e1")?;
        let e2 = [
            axis[1] * e1[2] - axis[2] * e1[1],
            axis[2] * e1[0] - axis[0] * e1[2],
            axis[0] * e1[1] - axis[1] * e1[0],
        ];
        let values = descriptor.as_array();
        let (rows, cols) = (values.nrows(), values.ncols());
        let mask = mask.as_array();
        if mask.shape() != values.shape() {
            return Err(PyValueError::new_err(format!(
                "`mask` must have the descriptor's shape ({rows}, {cols}), got {:?}",
                mask.shape()
            )));
        }
        // Default normals: those of a circle starting at e1 (p = 0) running towards e2.
        let circle = |f: fn(f64) -> f64| -> Vec<f64> {
            (0..cols)
                .map(|c| f(std::f64::consts::TAU * (c as f64 + 0.5) / cols as f64))
                .collect()
        };
        let contour = contour.map_or_else(|| Ok(Vec::new()), |c| contour_points(&c))?;
        let landmark = Landmark {
            submap_stamp,
            scan_stamps: scan_stamps
                .map(|s| vector(&s))
                .unwrap_or_else(|| vec![submap_stamp]),
            origin_in_submap: vec3(&origin, "origin")?,
            axis_in_submap: axis,
            e1_in_submap: e1,
            e2_in_submap: e2,
            contour_e1e2_m: contour,
            radius_m,
            strength,
            descriptor: Descriptor {
                rows,
                cols,
                cell_z_m,
                perimeter_m,
                offsets_m: values.iter().map(|&v| v as f32).collect(),
                observed: mask.iter().copied().collect(),
                normal_e1: normal_e1
                    .map(|n| vector(&n))
                    .unwrap_or_else(|| circle(f64::cos)),
                normal_e2: normal_e2
                    .map(|n| vector(&n))
                    .unwrap_or_else(|| circle(f64::sin)),
            },
        };
        landmark.validate().map_err(to_py_err)?;
        Ok(Self::new(landmark))
    }

    /// Stamp of the submap's anchor scan, seconds.
    #[getter]
    fn submap_stamp(&self) -> f64 {
        self.head().submap_stamp
    }
    /// Stamps of the scans accumulated into the submap, `(K,)`.
    #[getter]
    fn scan_stamps<'py>(&self, py: Python<'py>) -> Bound<'py, PyArray1<f64>> {
        PyArray1::from_slice(py, &self.head().scan_stamps)
    }
    /// Landmark origin in the submap frame, `(3,)` metres.
    #[getter]
    fn origin<'py>(&self, py: Python<'py>) -> Bound<'py, PyArray1<f64>> {
        PyArray1::from_slice(py, &self.head().origin_in_submap)
    }
    /// Unit corridor axis in the submap frame, `(3,)`.
    #[getter]
    fn axis<'py>(&self, py: Python<'py>) -> Bound<'py, PyArray1<f64>> {
        PyArray1::from_slice(py, &self.head().axis_in_submap)
    }
    /// Transverse basis vector e1 (gravity side) in the submap frame, `(3,)`.
    #[getter]
    fn e1<'py>(&self, py: Python<'py>) -> Bound<'py, PyArray1<f64>> {
        PyArray1::from_slice(py, &self.head().e1_in_submap)
    }
    /// Transverse basis vector e2 = axis x e1 in the submap frame, `(3,)`.
    #[getter]
    fn e2<'py>(&self, py: Python<'py>) -> Bound<'py, PyArray1<f64>> {
        PyArray1::from_slice(py, &self.head().e2_in_submap)
    }
    /// Reference contour at the column centres, `(cols, 2)` along (e1, e2) from the origin.
    #[getter]
    fn contour<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyArray2<f64>>> {
        rows_to_numpy(py, &self.whole()?.contour_e1e2_m)
    }
    /// Mean contour radius (section size), metres.
    #[getter]
    fn radius_m(&self) -> f64 {
        self.head().radius_m
    }
    /// Detection strength (DoG response at the peak), metres.
    #[getter]
    fn strength(&self) -> f64 {
        self.head().strength
    }
    /// Mean signed normal offsets, `(rows, cols)` metres (0 where unobserved); held in single
    /// precision (`decod::landmark::Descriptor::offsets_m`), given as float64.
    #[getter]
    fn descriptor<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyArray2<f64>>> {
        let l = self.whole()?;
        let d = &l.descriptor;
        let values = d.offsets_m.iter().map(|&v| f64::from(v)).collect();
        flat_to_numpy(py, values, d.rows, d.cols)
    }
    /// Observed-cell mask, `(rows, cols)` bool.
    #[getter]
    fn mask<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyArray2<bool>>> {
        let l = self.whole()?;
        let d = &l.descriptor;
        flat_to_numpy(py, d.observed.clone(), d.rows, d.cols)
    }
    /// n1(p) = n(p)^T e1 at the column centres, `(cols,)`.
    #[getter]
    fn normal_e1<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyArray1<f64>>> {
        Ok(PyArray1::from_slice(
            py,
            &self.whole()?.descriptor.normal_e1,
        ))
    }
    /// n2(p) = n(p)^T e2 at the column centres, `(cols,)`.
    #[getter]
    fn normal_e2<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyArray1<f64>>> {
        Ok(PyArray1::from_slice(
            py,
            &self.whole()?.descriptor.normal_e2,
        ))
    }
    /// Whether the cells wait on disk (`Spill.put`); they are read back when asked for.
    #[getter]
    fn on_disk(&self) -> bool {
        self.held.on_disk()
    }
    /// Axial cell size, metres.
    #[getter]
    fn cell_z_m(&self) -> f64 {
        self.head().descriptor.cell_z_m
    }
    /// Contour perimeter, metres.
    #[getter]
    fn perimeter_m(&self) -> f64 {
        self.head().descriptor.perimeter_m
    }
    /// The landmark as JSON (lossless; `Landmark.from_json` reads it back).
    fn to_json(&self) -> PyResult<String> {
        serde_json::to_string(&*self.whole()?).map_err(|e| PyValueError::new_err(e.to_string()))
    }
    /// Reads a landmark written by `to_json`.
    #[staticmethod]
    fn from_json(text: &str) -> PyResult<Self> {
        let landmark: Landmark = serde_json::from_str(text)
            .map_err(|e| PyValueError::new_err(format!("invalid landmark JSON: {e}")))?;
        landmark.validate().map_err(to_py_err)?;
        Ok(Self::new(landmark))
    }
    fn __repr__(&self) -> String {
        let l = self.head();
        let o = l.origin_in_submap;
        let cells = l.descriptor.rows * l.descriptor.cols;
        let observed = match &self.held {
            Held::Memory(l) => format!("{}/{cells}", l.descriptor.observed_count()),
            Held::Disk(_) => "on disk".into(),
        };
        format!(
            "Landmark(stamp={:.3}, origin=[{:.3}, {:.3}, {:.3}], strength={:.2e}, observed={observed})",
            l.submap_stamp, o[0], o[1], o[2], l.strength,
        )
    }
}

pub(crate) fn register(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_class::<PyLandmark>()?;
    m.add_class::<PySpill>()
}
