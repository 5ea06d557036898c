//! Types shared by extraction (producer) and matching (consumer): the descriptor grid and
//! the landmark that carries it. Frames are named: `*_in_submap` is the body frame of the
//! submap's anchor scan.

use serde::{Deserialize, Serialize};

/// A DeCOD descriptor (paper §III-A): the boundary neighbourhood unrolled on a `(z, p)` grid.
///
/// Row `r` covers axial offsets `z` in `[-half_length + r*cell_z_m, ... + cell_z_m)` from the
/// landmark origin along the axis; column `c` covers normalised arclength
/// `p` in `[c/cols, (c+1)/cols)`, starting at `e1` (gravity) and running towards `e2`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Descriptor {
    /// Number of axial bins `N_z` (16 by default).
    pub rows: usize,
    /// Number of circumferential bins `N_p` (256 by default).
    pub cols: usize,
    /// Axial cell size in metres (0.30 m in the tunnel preset).
    pub cell_z_m: f64,
    /// Contour perimeter in metres: converts a `p` offset into an arclength.
    pub perimeter_m: f64,
    /// Mean signed normal offset per cell in metres, row-major `rows x cols`;
    /// 0.0 where `observed` is false. Single precision, as a survey file stores it: a cell's
    /// mean is millimetres to decimetres of relief, so the f32's 1e-7 relative step is under
    /// a nanometre, and a run's landmarks (the part of its memory that grows with the log)
    /// take 16 KB less each (45 -> 29 KB; `docs/measurements.md`, "Long logs").
    pub offsets_m: Vec<f32>,
    /// Per-cell observed mask, row-major `rows x cols` (bottom sector forced false).
    pub observed: Vec<bool>,
    /// `n1(p) = n(p)^T e1` at each column centre (length `cols`), for normalisation.
    pub normal_e1: Vec<f64>,
    /// `n2(p) = n(p)^T e2` at each column centre (length `cols`).
    pub normal_e2: Vec<f64>,
}

impl Descriptor {
    /// Index of cell `(row, col)` in the row-major arrays.
    #[inline]
    pub fn index(&self, row: usize, col: usize) -> usize {
        row * self.cols + col
    }

    /// Number of observed cells.
    pub fn observed_count(&self) -> usize {
        self.observed.iter().filter(|&&o| o).count()
    }
}

/// A cross-sectional boundary detected in one submap, with everything matching and the
/// 5-DoF factor need.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Landmark {
    /// Stamp of the submap's anchor scan (seconds); identifies the frame below.
    pub submap_stamp: f64,
    /// Stamps of every scan accumulated into the submap (eligibility: no shared scans).
    pub scan_stamps: Vec<f64>,
    /// Landmark origin `o` (contour centre at the boundary) in the submap frame, metres.
    pub origin_in_submap: [f64; 3],
    /// Unit corridor axis `a` in the submap frame, oriented with the sensor's forward.
    pub axis_in_submap: [f64; 3],
    /// Transverse basis `e1` (gravity projected off the axis) in the submap frame.
    pub e1_in_submap: [f64; 3],
    /// Transverse basis `e2 = a x e1` in the submap frame.
    pub e2_in_submap: [f64; 3],
    /// Reference contour sampled at the descriptor's column centres: `(cols, 2)` row-major,
    /// coordinates along `(e1, e2)` relative to `origin_in_submap`, metres.
    pub contour_e1e2_m: Vec<[f64; 2]>,
    /// Characteristic size of the section: mean distance of the contour from its centre.
    pub radius_m: f64,
    /// DoG response at the boundary peak (metres of offset): detection strength.
    pub strength: f64,
    /// The descriptor around the boundary.
    pub descriptor: Descriptor,
}

impl Landmark {
    /// Checks the invariants matching relies on: grid sizes consistent, finite values,
    /// unit axis and orthonormal basis. Landmarks built in Python go through this.
    pub fn validate(&self) -> crate::Result<()> {
        use crate::error::DecodError;
        let d = &self.descriptor;
        let cells = d.rows * d.cols;
        if d.rows == 0 || d.cols == 0 {
            return Err(DecodError::invalid("descriptor", "empty grid"));
        }
        if d.offsets_m.len() != cells || d.observed.len() != cells {
            return Err(DecodError::invalid(
                "descriptor",
                format!(
                    "offsets/mask must have rows*cols = {cells} cells, got {} and {}",
                    d.offsets_m.len(),
                    d.observed.len()
                ),
            ));
        }
        if d.normal_e1.len() != d.cols || d.normal_e2.len() != d.cols {
            return Err(DecodError::invalid(
                "descriptor normals",
                format!("normal_e1/normal_e2 must have cols = {} entries", d.cols),
            ));
        }
        if !self.contour_e1e2_m.is_empty() && self.contour_e1e2_m.len() != d.cols {
            return Err(DecodError::invalid(
                "contour",
                format!("must have cols = {} points or none", d.cols),
            ));
        }
        let finite = |v: &[f64]| v.iter().all(|x| x.is_finite());
        if !d.offsets_m.iter().all(|x| x.is_finite())
            || !finite(&d.normal_e1)
            || !finite(&d.normal_e2)
            || !finite(&self.origin_in_submap)
            || !finite(&self.axis_in_submap)
            || !finite(&self.e1_in_submap)
            || !finite(&self.e2_in_submap)
            || !(self.submap_stamp.is_finite() && self.strength.is_finite())
        {
            return Err(DecodError::invalid("landmark", "non-finite values"));
        }
        if !(d.cell_z_m > 0.0 && d.perimeter_m > 0.0) {
            return Err(DecodError::invalid(
                "descriptor",
                "cell_z_m and perimeter_m must be > 0",
            ));
        }
        let dot = |a: &[f64; 3], b: &[f64; 3]| a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
        let (a, e1, e2) = (&self.axis_in_submap, &self.e1_in_submap, &self.e2_in_submap);
        let orthonormal = (dot(a, a) - 1.0).abs() < 1e-6
            && (dot(e1, e1) - 1.0).abs() < 1e-6
            && (dot(e2, e2) - 1.0).abs() < 1e-6
            && dot(a, e1).abs() < 1e-6
            && dot(a, e2).abs() < 1e-6
            && dot(e1, e2).abs() < 1e-6;
        if !orthonormal {
            return Err(DecodError::invalid(
                "axis/e1/e2",
                "must be an orthonormal basis (unit axis, e1 and e2 perpendicular to it)",
            ));
        }
        Ok(())
    }

    /// The landmark without its cells (the descriptor's offsets, mask and normals, and the
    /// contour): what a [`crate::spill::Held`] landmark keeps in memory. Not a valid landmark
    /// ([`Landmark::validate`] refuses it).
    pub fn head(&self) -> Landmark {
        let d = &self.descriptor;
        Landmark {
            scan_stamps: self.scan_stamps.clone(),
            contour_e1e2_m: Vec::new(),
            descriptor: Descriptor {
                rows: d.rows,
                cols: d.cols,
                cell_z_m: d.cell_z_m,
                perimeter_m: d.perimeter_m,
                offsets_m: Vec::new(),
                observed: Vec::new(),
                normal_e1: Vec::new(),
                normal_e2: Vec::new(),
            },
            ..*self
        }
    }
}
