//! Bindings for the map-consistency figure (`decod::map_quality`): the chainage of a map's
//! points and the wall thickness per bin, numpy in and out.

use numpy::{PyArray1, PyReadonlyArray1, PyReadonlyArray2};
use pyo3::exceptions::PyValueError;
use pyo3::prelude::*;

use super::arrays::{points_n3, vector};
use super::detached;
use crate::map_quality::{
    ChainageFrame, MIN_CELL_POINTS, point_chainage as chainage_of, wall_thickness as thickness,
};

/// Chainage `(N,)` metres of map points `(N, 3)`: each along the frame of its submap
/// (`submap` `(N,)` uint32 indexes the `(K, 3)` `origin` and `tangent` rows and the `(K,)`
/// `arclength`).
#[pyfunction]
fn point_chainage<'py>(
    py: Python<'py>,
    points: PyReadonlyArray2<'_, f64>,
    submap: PyReadonlyArray1<'_, u32>,
    origin: PyReadonlyArray2<'_, f64>,
    tangent: PyReadonlyArray2<'_, f64>,
    arclength: PyReadonlyArray1<'_, f64>,
) -> PyResult<Bound<'py, PyArray1<f64>>> {
    let points = points_n3(&points, "points")?;
    let submap: Vec<u32> = submap.as_array().iter().copied().collect();
    let origin = points_n3(&origin, "origin")?;
    let tangent = points_n3(&tangent, "tangent")?;
    let arclength = vector(&arclength);
    if tangent.len() != origin.len() || arclength.len() != origin.len() {
        return Err(PyValueError::new_err(format!(
            "origin, tangent and arclength must have one row per submap, got {}, {} and {}",
            origin.len(),
            tangent.len(),
            arclength.len()
        )));
    }
    let frames: Vec<ChainageFrame> = (0..origin.len())
        .map(|k| ChainageFrame {
            origin: origin[k],
            tangent: tangent[k],
            arclength: arclength[k],
        })
        .collect();
    let chainage = detached(py, || chainage_of(&points, &submap, &frames))?;
    Ok(PyArray1::from_vec(py, chainage))
}

/// `(start_m, overlap (B,), outbound floor (B,), return floor (B,))`: the wall thickness
/// in metres per bin of `bin_m` from `start_m`, NaN where the passes do not both reach.
type ThicknessArrays<'py> = (
    f64,
    Bound<'py, PyArray1<f64>>,
    Bound<'py, PyArray1<f64>>,
    Bound<'py, PyArray1<f64>>,
);

/// Wall thickness where both passes of a map reach, per `bin_m` of `chainage`, in cells of
/// edge `cell_m`: `points` `(N, 3)`, `pass_` `(N,)` uint8 (0 outbound, 1 return),
/// `chainage` `(N,)` metres.
#[pyfunction]
fn wall_thickness<'py>(
    py: Python<'py>,
    points: PyReadonlyArray2<'_, f64>,
    pass_: PyReadonlyArray1<'_, u8>,
    chainage: PyReadonlyArray1<'_, f64>,
    cell_m: f64,
    bin_m: f64,
) -> PyResult<ThicknessArrays<'py>> {
    let points = points_n3(&points, "points")?;
    let pass: Vec<u8> = pass_.as_array().iter().copied().collect();
    let chainage = vector(&chainage);
    let t = detached(py, || thickness(&points, &pass, &chainage, cell_m, bin_m))?;
    let [outbound, ret] = t.floor_m;
    Ok((
        t.start_m,
        PyArray1::from_vec(py, t.overlap_m),
        PyArray1::from_vec(py, outbound),
        PyArray1::from_vec(py, ret),
    ))
}

pub(crate) fn register(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add("MIN_CELL_POINTS", MIN_CELL_POINTS)?;
    m.add_function(wrap_pyfunction!(point_chainage, m)?)?;
    m.add_function(wrap_pyfunction!(wall_thickness, m)?)?;
    Ok(())
}
