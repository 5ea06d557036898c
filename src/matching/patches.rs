//! Gaussian-weighted local patches of the compared field (paper §III-B: 9 x 33 patches,
//! Gaussian weights sigma_z, sigma_p, distance over mutually observed cells): their shape,
//! z-score and compact storage. Their distances, as matrix products, are in
//! [`super::patch_distances`].
//!
//! Patch normalisation (the paper is silent): each patch is z-scored (Gaussian-weighted mean
//! and standard deviation over its own observed cells), so a distance compares texture shape,
//! not local amplitude (which varies with incidence angle and range); flat patches
//! (std below 1e-9 of the field's scale) keep their raw, mean-removed values.
//!
//! The patches depend only on the landmark, so they are z-scored once when a landmark is
//! added to a database and kept compact (the compared field and each keypoint's centre and
//! z-score); the factors of the distances' matrix products are built from them per
//! comparison (the candidate's) or once per query. Under `h = 180` the query patches are
//! flipped (flat reversal, see `heading.rs`) instead of the candidate's, so the database
//! stores one set of patches per landmark.

use super::keypoints::Keypoint;
use std::path::Path;

use crate::config::MatchingConfig;
use crate::error::Result;
use crate::survey::{Reader, err};

/// Patch geometry shared by every landmark of one config.
#[derive(Clone, Debug, PartialEq)]
pub struct PatchShape {
    /// Patch rows (odd).
    pub rows: usize,
    /// Patch columns (odd).
    pub cols: usize,
    /// Gaussian weights, flat row-major `rows x cols`, max 1 at the centre.
    pub weights: Vec<f32>,
    /// Sum of the weights.
    pub weight_sum: f64,
}

impl PatchShape {
    /// From the config (even sizes are rounded up to odd so that patches have a centre cell).
    pub fn new(cfg: &MatchingConfig) -> Self {
        let rows = cfg.patch_rows | 1;
        let cols = cfg.patch_cols | 1;
        let (hr, hc) = ((rows / 2) as f64, (cols / 2) as f64);
        let mut weights = Vec::with_capacity(rows * cols);
        for r in 0..rows {
            for c in 0..cols {
                let (dz, dp) = (r as f64 - hr, c as f64 - hc);
                let w = (-0.5
                    * (dz * dz / (cfg.sigma_z_cells * cfg.sigma_z_cells)
                        + dp * dp / (cfg.sigma_p_cells * cfg.sigma_p_cells)))
                    .exp();
                weights.push(w as f32);
            }
        }
        let weight_sum = weights.iter().map(|&w| f64::from(w)).sum();
        Self {
            rows,
            cols,
            weights,
            weight_sum,
        }
    }

    /// Number of cells `P` in a patch.
    pub fn len(&self) -> usize {
        self.rows * self.cols
    }

    /// Always false (a patch has at least one cell); for clippy's `len_without_is_empty`.
    pub fn is_empty(&self) -> bool {
        false
    }

    /// Gaussian-weighted fraction of the patch centred at `(row, col)` that is observed.
    pub fn coverage(&self, observed: &[bool], grid: (usize, usize), row: usize, col: usize) -> f64 {
        let mut acc = 0.0;
        self.visit(grid, row, col, |k, cell| {
            if let Some(i) = cell
                && observed[i]
            {
                acc += f64::from(self.weights[k]);
            }
        });
        acc / self.weight_sum
    }

    /// The patch rows `[lo, hi)` of a patch centred on field row `row` that lie within a
    /// field of `field_rows` rows (the rest reach beyond its axial ends).
    pub fn rows_within(&self, row: usize, field_rows: usize) -> (usize, usize) {
        let half = self.rows / 2;
        let lo = half.saturating_sub(row).min(self.rows);
        let hi = (field_rows + half).saturating_sub(row).min(self.rows);
        (lo, hi.max(lo))
    }

    /// Whether every cell of the patch centred at `(row, col)` that lies within the field is
    /// observed: the patch is then *banded*, its mask one on [`Self::rows_within`] and zero
    /// elsewhere, known without reading it (`super::patch_distances`).
    pub fn is_banded(
        &self,
        observed: &[bool],
        grid: (usize, usize),
        row: usize,
        col: usize,
    ) -> bool {
        let mut banded = true;
        self.visit(grid, row, col, |_, cell| {
            if let Some(i) = cell {
                banded &= observed[i];
            }
        });
        banded
    }

    /// Calls `f(k, cell)` for each patch position `k` with the grid cell index it covers
    /// (`None` beyond the axial ends; columns wrap around the circumference).
    fn visit(
        &self,
        grid: (usize, usize),
        row: usize,
        col: usize,
        mut f: impl FnMut(usize, Option<usize>),
    ) {
        let (grows, gcols) = (grid.0 as isize, grid.1 as isize);
        let (hr, hc) = ((self.rows / 2) as isize, (self.cols / 2) as isize);
        let mut k = 0;
        for dr in -hr..=hr {
            let r = row as isize + dr;
            for dc in -hc..=hc {
                let cell = if r >= 0 && r < grows {
                    let c = super::keypoints::wrap_col(col, dc, grid.1) as isize;
                    Some((r * gcols + c) as usize)
                } else {
                    None
                };
                f(k, cell);
                k += 1;
            }
        }
    }

    /// The z-score of the patch centred at `kp` over its observed cells: the
    /// Gaussian-weighted mean and the inverse of the weighted standard deviation (1 for a flat
    /// patch, whose values keep their amplitude; `(0, 1)` for a patch with no observed cell).
    pub fn z_score(
        &self,
        field: &[f64],
        observed: &[bool],
        grid: (usize, usize),
        kp: &Keypoint,
    ) -> (f64, f64) {
        let (mut sw, mut swa) = (0.0, 0.0);
        let mut cells = Vec::with_capacity(self.len());
        self.visit(grid, kp.row, kp.col, |k, cell| {
            if let Some(i) = cell
                && observed[i]
            {
                let w = f64::from(self.weights[k]);
                sw += w;
                swa += w * field[i];
                cells.push((w, field[i]));
            }
        });
        if sw <= 0.0 {
            return (0.0, 1.0);
        }
        let mean = swa / sw;
        let var = cells
            .iter()
            .map(|&(w, v)| w * (v - mean).powi(2))
            .sum::<f64>()
            / sw;
        let scale = if var.sqrt() > 1e-9 {
            1.0 / var.sqrt()
        } else {
            1.0
        };
        (mean, scale)
    }

    /// The z-scored patch values and mask at one keypoint (flat, length `P`), in f64: the
    /// reference that [`CandidatePatches::patch_into`] reproduces in f32 (tests).
    #[cfg(test)]
    pub fn extract(
        &self,
        field: &[f64],
        observed: &[bool],
        grid: (usize, usize),
        kp: &Keypoint,
    ) -> (Vec<f64>, Vec<bool>) {
        let p = self.len();
        let (mean, scale) = self.z_score(field, observed, grid, kp);
        let (mut values, mut mask) = (vec![0.0; p], vec![false; p]);
        self.visit(grid, kp.row, kp.col, |k, cell| {
            if let Some(i) = cell
                && observed[i]
            {
                values[k] = (field[i] - mean) * scale;
                mask[k] = true;
            }
        });
        (values, mask)
    }
}

/// Where one keypoint's patch lies on the compared field and how it is z-scored
/// ([`PatchShape::z_score`]).
#[derive(Clone, Copy, Debug, PartialEq)]
struct PatchCentre {
    row: u32,
    col: u32,
    mean: f64,
    scale: f64,
    /// [`PatchShape::is_banded`].
    banded: bool,
}

/// The candidate side of one landmark's keypoint patches, kept compact: the compared field
/// once (`rows x cols` f32, NaN where unobserved) and each keypoint's centre and z-score. A
/// keypoint's patch `b` ([`Self::patch_into`], `P` values) and the candidate's factor of the
/// distances' matrix products (`super::patch_distances::PatchFactor`) are built from them
/// for the comparison that needs them. The patches overlap: 64 keypoints' 9 x 33 cells are 4.6
/// times the 16 x 256 field, so the field's 16 KB replace about 43 KB of patch values on
/// the full tier's landmarks (a landmark with its prepared view 76 -> 50 KB, the same 49-50
/// KB in every corridor and sensor; `docs/measurements.md`, "Long logs"), for about 2 % of a
/// pair (`cargo bench --bench matcher`). The values are the f64 reference's
/// (`PatchShape::extract`, in tests) from the field rounded to f32, within about 1e-6 of
/// them; before that, the values themselves were kept instead of the factor, a third of its
/// floats (`docs/decisions.md`, "Coarse retrieval for large databases").
#[derive(Clone, Debug)]
pub struct CandidatePatches {
    /// The compared field, row-major, NaN where unobserved.
    field: Vec<f32>,
    /// `(rows, cols)` of the field.
    grid: (usize, usize),
    /// One per keypoint, in the keypoints' order.
    centres: Vec<PatchCentre>,
}

impl CandidatePatches {
    /// The patches of `keypoints` on `field` (the compared field, `grid`, with its
    /// `observed` mask).
    pub fn new(
        shape: &PatchShape,
        field: &[f64],
        observed: &[bool],
        grid: (usize, usize),
        keypoints: &[Keypoint],
    ) -> Self {
        let centres = keypoints
            .iter()
            .map(|kp| {
                let (mean, scale) = shape.z_score(field, observed, grid, kp);
                PatchCentre {
                    row: kp.row as u32,
                    col: kp.col as u32,
                    mean,
                    scale,
                    banded: shape.is_banded(observed, grid, kp.row, kp.col),
                }
            })
            .collect();
        let field = field
            .iter()
            .zip(observed)
            .map(|(&v, &o)| if o { v as f32 } else { f32::NAN })
            .collect();
        Self {
            field,
            grid,
            centres,
        }
    }

    /// Number of keypoints `N`.
    pub fn count(&self) -> usize {
        self.centres.len()
    }

    /// Whether keypoint `j`'s patch is banded ([`PatchShape::is_banded`]).
    pub fn is_banded(&self, j: usize) -> bool {
        self.centres[j].banded
    }

    /// Keypoint `j`'s patch rows within the field ([`PatchShape::rows_within`]).
    pub fn rows_within(&self, shape: &PatchShape, j: usize) -> (usize, usize) {
        shape.rows_within(self.centres[j].row as usize, self.grid.0)
    }

    /// Heap bytes held (the field and the centres).
    pub fn heap_bytes(&self) -> usize {
        4 * self.field.len() + self.centres.len() * std::mem::size_of::<PatchCentre>()
    }

    /// The patches as bytes, exactly (little-endian: rows, cols and the keypoint count as
    /// u32, the field's f32, then each centre's row and column as u32, mean and scale as f64
    /// and the banded flag as a byte): what a view keeps on disk ([`crate::spill`]).
    pub(crate) fn encode(&self, out: &mut Vec<u8>) {
        let (rows, cols) = self.grid;
        for n in [rows, cols, self.centres.len()] {
            out.extend_from_slice(&(n as u32).to_le_bytes());
        }
        for v in &self.field {
            out.extend_from_slice(&v.to_le_bytes());
        }
        for c in &self.centres {
            out.extend_from_slice(&c.row.to_le_bytes());
            out.extend_from_slice(&c.col.to_le_bytes());
            out.extend_from_slice(&c.mean.to_le_bytes());
            out.extend_from_slice(&c.scale.to_le_bytes());
            out.push(u8::from(c.banded));
        }
    }

    /// The patches [`Self::encode`] wrote into `bytes`; a record of other sizes is an error
    /// naming `path`, refused before anything is allocated for it.
    pub(crate) fn decode(bytes: &[u8], path: &Path) -> Result<Self> {
        const CENTRE: usize = 4 + 4 + 8 + 8 + 1;
        let mut r = Reader::new(bytes, path);
        let (rows, cols, count) = (r.u32()? as usize, r.u32()? as usize, r.u32()? as usize);
        let cells = rows.saturating_mul(cols);
        if cells
            .saturating_mul(4)
            .saturating_add(count.saturating_mul(CENTRE))
            != r.left()
        {
            return Err(err(
                path,
                format!(
                    "a view's record of {} bytes for {rows} x {cols} and {count} keypoints",
                    bytes.len()
                ),
            ));
        }
        let f32_at = |b: &[u8]| f32::from_le_bytes([b[0], b[1], b[2], b[3]]);
        let field = r.take(4 * cells)?.chunks_exact(4).map(f32_at).collect();
        let centres = r
            .take(count * CENTRE)?
            .chunks_exact(CENTRE)
            .map(|c| {
                let u = |i: usize| u32::from_le_bytes([c[i], c[i + 1], c[i + 2], c[i + 3]]);
                let f = |i: usize| {
                    f64::from_le_bytes([
                        c[i],
                        c[i + 1],
                        c[i + 2],
                        c[i + 3],
                        c[i + 4],
                        c[i + 5],
                        c[i + 6],
                        c[i + 7],
                    ])
                };
                PatchCentre {
                    row: u(0),
                    col: u(4),
                    mean: f(8),
                    scale: f(16),
                    banded: c[24] != 0,
                }
            })
            .collect();
        Ok(Self {
            field,
            grid: (rows, cols),
            centres,
        })
    }

    /// Keypoint `j`'s z-scored patch in `out` (`P` values, flat row-major; NaN where the cell
    /// is unobserved or beyond the field's axial ends; columns wrap around the circumference).
    pub fn patch_into(&self, shape: &PatchShape, j: usize, out: &mut [f32]) {
        pulp::Arch::new().dispatch(FillPatch {
            patches: self,
            shape,
            j,
            out,
        });
    }
}

/// The body of [`CandidatePatches::patch_into`]: a patch row is one or two runs of the
/// field's row (two where it wraps around the circumference), each a branch-free map that the
/// compiler vectorises under [`pulp`] dispatch (a NaN stays NaN).
struct FillPatch<'a> {
    patches: &'a CandidatePatches,
    shape: &'a PatchShape,
    j: usize,
    out: &'a mut [f32],
}

impl pulp::WithSimd for FillPatch<'_> {
    type Output = ();

    #[inline(always)]
    fn with_simd<S: pulp::Simd>(self, _simd: S) {
        let CandidatePatches {
            field,
            grid: (rows, cols),
            centres,
        } = self.patches;
        let c = centres[self.j];
        let (prows, pcols) = (self.shape.rows, self.shape.cols);
        let z = |v: f32| ((f64::from(v) - c.mean) * c.scale) as f32;
        let run = |src: &[f32], dst: &mut [f32]| {
            for (o, &v) in dst.iter_mut().zip(src) {
                *o = z(v);
            }
        };
        if *cols == 0 {
            self.out.fill(f32::NAN);
            return;
        }
        let first_col = (c.col as usize % cols + cols - (pcols / 2) % cols) % cols;
        for (dr, out_row) in self.out.chunks_exact_mut(pcols).take(prows).enumerate() {
            let r = (c.row as usize + dr).checked_sub(prows / 2);
            let Some(row) = r
                .filter(|&r| r < *rows)
                .map(|r| &field[r * cols..(r + 1) * cols])
            else {
                out_row.fill(f32::NAN);
                continue;
            };
            if pcols > *cols {
                // A patch wider than the field (a grid no config of ours makes): cell by cell.
                for (dc, o) in out_row.iter_mut().enumerate() {
                    *o = z(row[(first_col + dc) % cols]);
                }
                continue;
            }
            let head = (cols - first_col).min(pcols);
            let (near, far) = out_row.split_at_mut(head);
            run(&row[first_col..first_col + head], near);
            run(&row[..pcols - head], far);
        }
    }
}

/// Brute-force f64 reference of [`super::patch_distances::distances`] for one pair of
/// patches (tests, docs).
pub fn distance_reference(
    shape: &PatchShape,
    a: &(Vec<f64>, Vec<bool>),
    b: &(Vec<f64>, Vec<bool>),
    min_overlap: f64,
) -> f64 {
    let (mut num, mut den) = (0.0, 0.0);
    for k in 0..shape.len() {
        if a.1[k] && b.1[k] {
            let w = f64::from(shape.weights[k]);
            num += w * (a.0[k] - b.0[k]).powi(2);
            den += w;
        }
    }
    if den >= min_overlap * shape.weight_sum && den > 0.0 {
        num / den
    } else {
        f64::INFINITY
    }
}
