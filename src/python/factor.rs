//! Bindings for the landmark factor's residual (`decod::landmark_factor`), called by the
//! graph's `gtsam.CustomFactor` at every linearisation: numpy in and out.

use nalgebra::{Matrix4, Vector3};
use numpy::{PyArray1, PyArray2, PyReadonlyArray1, PyReadonlyArray2};
use pyo3::prelude::*;

use super::arrays::{fixed_matrix, flat_to_numpy, vec3};
use crate::landmark_factor::{Jacobian, LandmarkPair, RESIDUAL_DIM, landmark_residual as residual};

fn jacobian_to_numpy<'py>(py: Python<'py>, h: &Jacobian) -> PyResult<Bound<'py, PyArray2<f64>>> {
    let rows: Vec<f64> = (0..RESIDUAL_DIM)
        .flat_map(|r| (0..6).map(move |c| h[(r, c)]))
        .collect();
    flat_to_numpy(py, rows, RESIDUAL_DIM, 6)
}

/// `(residual (4,), H_i (4, 6) | None, H_j (4, 6) | None)`.
type Residual<'py> = (
    Bound<'py, PyArray1<f64>>,
    Option<Bound<'py, PyArray2<f64>>>,
    Option<Bound<'py, PyArray2<f64>>>,
);

/// The 5-DoF landmark residual `[frame (T_ij c_j - c_i), 1 - (a_i' R_ij a_j)^2]` of poses
/// `world_from_i`, `world_from_j` `(4, 4)` and, with `jacobians`, its `(4, 6)` Jacobians in
/// GTSAM's Pose3 tangent order `[w, v]`. `frame` `(3, 3)` rotates the position rows.
#[pyfunction]
#[pyo3(signature = (world_from_i, world_from_j, c_i, a_i, c_j, a_j, frame, jacobians = false))]
#[allow(clippy::too_many_arguments)]
fn landmark_residual<'py>(
    py: Python<'py>,
    world_from_i: PyReadonlyArray2<'_, f64>,
    world_from_j: PyReadonlyArray2<'_, f64>,
    c_i: PyReadonlyArray1<'_, f64>,
    a_i: PyReadonlyArray1<'_, f64>,
    c_j: PyReadonlyArray1<'_, f64>,
    a_j: PyReadonlyArray1<'_, f64>,
    frame: PyReadonlyArray2<'_, f64>,
    jacobians: bool,
) -> PyResult<Residual<'py>> {
    let ti: Matrix4<f64> = fixed_matrix(&world_from_i, "world_from_i")?;
    let tj: Matrix4<f64> = fixed_matrix(&world_from_j, "world_from_j")?;
    let pair = LandmarkPair {
        c_i: Vector3::from(vec3(&c_i, "c_i")?),
        a_i: Vector3::from(vec3(&a_i, "a_i")?),
        c_j: Vector3::from(vec3(&c_j, "c_j")?),
        a_j: Vector3::from(vec3(&a_j, "a_j")?),
        frame: fixed_matrix(&frame, "frame")?,
    };
    let (res, jac) = residual(&ti, &tj, &pair, jacobians);
    let res = PyArray1::from_slice(py, res.as_slice());
    match jac {
        Some((hi, hj)) => Ok((
            res,
            Some(jacobian_to_numpy(py, &hi)?),
            Some(jacobian_to_numpy(py, &hj)?),
        )),
        None => Ok((res, None, None)),
    }
}

pub(crate) fn register(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_function(wrap_pyfunction!(landmark_residual, m)?)?;
    Ok(())
}
