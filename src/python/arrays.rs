//! numpy in and out. Inputs are shape-checked with errors that name the argument and the
//! expected shape, and read through safe (stride-aware) views; outputs are moved into numpy
//! without copying.

use numpy::ndarray::Array2;
use numpy::{IntoPyArray, PyArray2, PyReadonlyArray1, PyReadonlyArray2};
use pyo3::exceptions::PyValueError;
use pyo3::prelude::*;

/// `(N, K)` float64 rows into owned arrays; `name` is the argument named in the error.
/// Non-finite values are left for the core to report (it knows which index and why it
/// matters).
pub(crate) fn rows_n<const K: usize>(
    array: &PyReadonlyArray2<'_, f64>,
    name: &str,
) -> PyResult<Vec<[f64; K]>> {
    let view = array.as_array();
    if view.ncols() != K {
        return Err(PyValueError::new_err(format!(
            "`{name}` must have shape (N, {K}), got {:?}",
            view.shape()
        )));
    }
    Ok(view
        .rows()
        .into_iter()
        .map(|r| std::array::from_fn(|i| r[i]))
        .collect())
}

/// `(N, 3)` float64 points into owned rows ([`rows_n`]).
pub(crate) fn points_n3(array: &PyReadonlyArray2<'_, f64>, name: &str) -> PyResult<Vec<[f64; 3]>> {
    rows_n(array, name)
}

/// `(4, 4)` float64 homogeneous matrix into a row-major array.
pub(crate) fn matrix_4x4(array: &PyReadonlyArray2<'_, f64>, name: &str) -> PyResult<[f64; 16]> {
    let view = array.as_array();
    if view.shape() != [4, 4] {
        return Err(PyValueError::new_err(format!(
            "`{name}` must have shape (4, 4), got {:?}",
            view.shape()
        )));
    }
    let mut out = [0.0; 16];
    for ((r, c), v) in view.indexed_iter() {
        out[r * 4 + c] = *v;
    }
    Ok(out)
}

/// `(3,)` float64 vector into an array; `name` is the argument named in the error.
pub(crate) fn vec3(array: &PyReadonlyArray1<'_, f64>, name: &str) -> PyResult<[f64; 3]> {
    let v = vector(array);
    <[f64; 3]>::try_from(v.as_slice()).map_err(|_| {
        PyValueError::new_err(format!("`{name}` must have shape (3,), got ({},)", v.len()))
    })
}

/// `(R, C)` float64 array into a fixed-size matrix; `name` is the argument named in the
/// error.
pub(crate) fn fixed_matrix<const R: usize, const C: usize>(
    array: &PyReadonlyArray2<'_, f64>,
    name: &str,
) -> PyResult<nalgebra::SMatrix<f64, R, C>> {
    let view = array.as_array();
    if view.shape() != [R, C] {
        return Err(PyValueError::new_err(format!(
            "`{name}` must have shape ({R}, {C}), got {:?}",
            view.shape()
        )));
    }
    Ok(nalgebra::SMatrix::from_fn(|r, c| view[[r, c]]))
}

/// `(N,)` float64 vector into an owned Vec.
pub(crate) fn vector(array: &PyReadonlyArray1<'_, f64>) -> Vec<f64> {
    array.as_array().iter().copied().collect()
}

/// Rows of `K` values into a `(N, K)` numpy array (moved, not copied).
pub(crate) fn rows_to_numpy<'py, const K: usize>(
    py: Python<'py>,
    rows: &[[f64; K]],
) -> PyResult<Bound<'py, PyArray2<f64>>> {
    let flat: Vec<f64> = rows.iter().flat_map(|r| r.iter().copied()).collect();
    flat_to_numpy(py, flat, rows.len(), K)
}

/// A row-major buffer into a `(rows, cols)` numpy array (moved, not copied).
pub(crate) fn flat_to_numpy<'py, T: numpy::Element>(
    py: Python<'py>,
    flat: Vec<T>,
    rows: usize,
    cols: usize,
) -> PyResult<Bound<'py, PyArray2<T>>> {
    Array2::from_shape_vec((rows, cols), flat)
        .map(|a| a.into_pyarray(py))
        .map_err(|e| PyValueError::new_err(format!("internal shape error: {e}")))
}

/// IMU samples as `(N, 4)` rows: stamp (s) and specific force (m/s^2); `None` without an
/// IMU. What a stream read once, handed to a later stream of the same log (`imu_samples=`).
pub(crate) fn imu_to_numpy<'py>(
    py: Python<'py>,
    samples: Option<&[crate::io::imu::ImuSample]>,
) -> PyResult<Option<Bound<'py, PyArray2<f64>>>> {
    let Some(samples) = samples else {
        return Ok(None);
    };
    let rows: Vec<[f64; 4]> = samples
        .iter()
        .map(|s| {
            let f = s.specific_force;
            [s.stamp, f[0], f[1], f[2]]
        })
        .collect();
    rows_to_numpy(py, &rows).map(Some)
}
