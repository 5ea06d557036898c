//! Gaussian-weighted local patches and their masked distances as matrix products
//! (paper §III-B: 9 x 33 patches, Gaussian weights sigma_z, sigma_p, distance over mutually
//! observed cells).
//!
//! For a query patch `a` with mask `m_a` and a candidate patch `b` with mask `m_b` (flat
//! vectors of `P = patch_rows * patch_cols` cells, weights `w`), the distance is the weighted
//! mean squared difference over mutually observed cells:
//!
//! `d(a, b) = sum w m_a m_b (a - b)^2 / sum w m_a m_b`, and `+inf` when the mutual weight
//! `sum w m_a m_b` is below `min_patch_overlap_fraction * sum w`.
//!
//! The numerator expands into `(w m_a a^2) . m_b + m_a . (w m_b b^2) - 2 (w m_a a) . (m_b b)`,
//! so for all keypoint pairs at once it is ONE matrix product with inner size `3P`:
//! `[w m_a a^2 | m_a | w m_a a] (N_i x 3P)  x  [m_b ; w m_b b^2 ; -2 m_b b] (3P x N_j)`,
//! and the denominator is a second one, `[w m_a] (N_i x P) x [m_b] (P x N_j)`, whose right
//! factor is the first block of the candidate matrix. Both go to faer's GEMM in f32 (offsets
//! are z-scored per patch, so f32 keeps ~1e-6 relative precision; checked against a
//! brute-force f64 reference in the tests).
//!
//! Patch normalisation (the paper is silent): each patch is z-scored (Gaussian-weighted mean
//! and standard deviation over its own observed cells), so a distance compares texture shape,
//! not local amplitude (which varies with incidence angle and range); flat patches
//! (std below 1e-9 of the field's scale) keep their raw, mean-removed values.
//!
//! The patches depend only on the landmark, so they are z-scored once when a landmark is
//! added to a database and kept compact (the compared field and each keypoint's centre and
//! z-score); the candidate matrix is built from them per comparison, the query factors once
//! per query. Under `h = 180` the query patches are flipped (flat reversal, see `heading.rs`)
//! instead of the candidate's, so the database stores one set of patches per landmark.

use faer::linalg::matmul::matmul;
use faer::{Accum, Mat, MatRef, Par};

use super::keypoints::Keypoint;
use crate::config::MatchingConfig;

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
}

/// The candidate side of one landmark's keypoint patches, kept compact: the compared field
/// once (`rows x cols` f32, NaN where unobserved) and each keypoint's centre and z-score. A
/// keypoint's patch `b` ([`Self::patch_into`], `P` values) and the GEMM's factor
/// `[m_b ; w m_b b^2 ; -2 m_b b]` (`3P x N`, [`Self::factor_into`]) are built from them for
/// the comparison that needs them. The patches overlap: 64 keypoints' 9 x 33 cells are 4.6
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

    /// Heap bytes held (the field and the centres).
    pub fn heap_bytes(&self) -> usize {
        4 * self.field.len() + self.centres.len() * std::mem::size_of::<PatchCentre>()
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

    /// Builds the candidate factor `[m_b ; w m_b b^2 ; -2 m_b b]` (`3P x N`) of
    /// [`distances`] in `buf`, resized to it (reused from comparison to comparison: a fresh
    /// 180-230 KB matrix a pair cost a third of the pair's time in page faults and zeroing).
    /// Every entry is written.
    pub fn factor_into(&self, shape: &PatchShape, buf: &mut Mat<f32>) {
        buf.resize_with(3 * shape.len(), self.count(), |_, _| 0.0);
        let mut patch = vec![0.0f32; shape.len()];
        for j in 0..self.count() {
            self.patch_into(shape, j, &mut patch);
            pulp::Arch::new().dispatch(FillFactor {
                values: &patch,
                weights: &shape.weights,
                column: buf.col_as_slice_mut(j),
            });
        }
    }

    /// The factor as an owned matrix (tests, one-off comparisons).
    pub fn factor(&self, shape: &PatchShape) -> Mat<f32> {
        let mut buf = Mat::new();
        self.factor_into(shape, &mut buf);
        buf
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

/// The body of [`CandidatePatches::factor_into`] for one keypoint: branch-free (an
/// unobserved cell's NaN masked to +0 bit by bit, as the zeros the factor was once initialised
/// with), so that the compiler vectorises it at the CPU's width under [`pulp`] dispatch, as
/// [`Ratio`].
struct FillFactor<'a> {
    values: &'a [f32],
    weights: &'a [f32],
    column: &'a mut [f32],
}

impl pulp::WithSimd for FillFactor<'_> {
    type Output = ();

    #[inline(always)]
    fn with_simd<S: pulp::Simd>(self, _simd: S) {
        let p = self.weights.len();
        let (mask, rest) = self.column.split_at_mut(p);
        let (square, rest) = rest.split_at_mut(p);
        let cells = self.values.iter().zip(self.weights);
        let out = mask.iter_mut().zip(square.iter_mut()).zip(rest.iter_mut());
        for ((&b, &w), ((m, sq), lin)) in cells.zip(out) {
            let keep = 0u32.wrapping_sub(u32::from(!b.is_nan()));
            *m = f32::from_bits(1.0f32.to_bits() & keep);
            *sq = f32::from_bits((w * b * b).to_bits() & keep);
            *lin = f32::from_bits((-2.0 * b).to_bits() & keep);
        }
    }
}

/// The query factors of one landmark under one heading: `[w m_a a^2 | m_a | w m_a a]`
/// (`N x 3P`, numerator) and `[w m_a]` (`N x P`, denominator), built from its patches
/// ([`CandidatePatches`]); `flipped` reverses each patch (heading 180°).
#[derive(Clone, Debug)]
pub struct QueryPatches {
    /// `N x 3P`.
    pub numerator: Mat<f32>,
    /// `N x P`.
    pub denominator: Mat<f32>,
}

impl QueryPatches {
    /// Rearranges a landmark's candidate patches into query factors.
    pub fn from_candidate(shape: &PatchShape, cand: &CandidatePatches, flipped: bool) -> Self {
        let p = shape.len();
        let n = cand.count();
        let mut numerator = Mat::<f32>::zeros(n, 3 * p);
        let mut denominator = Mat::<f32>::zeros(n, p);
        let mut values = vec![0.0f32; p];
        for i in 0..n {
            cand.patch_into(shape, i, &mut values);
            for k in 0..p {
                // Source position: reversed patch under the flip; weights are symmetric.
                let src = if flipped { p - 1 - k } else { k };
                let a = values[src];
                if !a.is_nan() {
                    let w = shape.weights[k];
                    numerator[(i, k)] = w * a * a;
                    numerator[(i, p + k)] = 1.0;
                    numerator[(i, 2 * p + k)] = w * a;
                    denominator[(i, k)] = w;
                }
            }
        }
        Self {
            numerator,
            denominator,
        }
    }

    /// Number of keypoints `N`.
    pub fn count(&self) -> usize {
        self.numerator.nrows()
    }
}

/// All patch distances `N_i x N_j` between query and candidate keypoints (two GEMMs);
/// `+inf` where the mutually observed weight is below `min_overlap * sum w`. `cand`: the
/// candidate's factor ([`CandidatePatches::factor`]).
pub fn distances(
    shape: &PatchShape,
    query: &QueryPatches,
    cand: MatRef<'_, f32>,
    min_overlap: f64,
) -> Mat<f32> {
    let (ni, nj, p) = (query.count(), cand.ncols(), shape.len());
    let mut num = Mat::<f32>::zeros(ni, nj);
    let mut den = Mat::<f32>::zeros(ni, nj);
    if ni == 0 || nj == 0 {
        return num;
    }
    matmul(
        num.as_mut(),
        Accum::Replace,
        query.numerator.as_ref(),
        cand,
        1.0f32,
        Par::Seq,
    );
    let cand_mask: MatRef<'_, f32> = cand.subrows(0, p);
    matmul(
        den.as_mut(),
        Accum::Replace,
        query.denominator.as_ref(),
        cand_mask,
        1.0f32,
        Par::Seq,
    );
    let min_weight = (min_overlap * shape.weight_sum) as f32;
    pulp::Arch::new().dispatch(Ratio {
        num: &mut num,
        den: &den,
        min_weight,
    });
    num
}

/// The division pass of [`distances`] (`num <- max(num, 0) / den`, `+inf` where `den` is
/// below `min_weight`): column slices and a branch-free body that the compiler vectorises,
/// under [`pulp`] dispatch so at the CPU's full width (IEEE division: the same bits on every
/// instruction set).
struct Ratio<'a> {
    num: &'a mut Mat<f32>,
    den: &'a Mat<f32>,
    min_weight: f32,
}

impl pulp::WithSimd for Ratio<'_> {
    type Output = ();

    #[inline(always)]
    fn with_simd<S: pulp::Simd>(self, _simd: S) {
        for j in 0..self.num.ncols() {
            let dens = self.den.col_as_slice(j);
            for (n, &d) in self.num.col_as_slice_mut(j).iter_mut().zip(dens) {
                let ratio = n.max(0.0) / d;
                *n = if d >= self.min_weight && d > 0.0 {
                    ratio
                } else {
                    f32::INFINITY
                };
            }
        }
    }
}

/// Brute-force f64 reference of [`distances`] for one pair of patches (tests, docs).
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
