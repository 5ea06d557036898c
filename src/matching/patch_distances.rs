//! The masked distances of all keypoint patches of a landmark pair as matrix products
//! (paper §III-B: Gaussian-weighted 9 x 33 patches compared over mutually observed cells).
//!
//! For a query patch `a` with mask `m_a` and a candidate patch `b` with mask `m_b` (flat
//! vectors of `P = patch_rows * patch_cols` cells, weights `w`), the distance is the weighted
//! mean squared difference over mutually observed cells:
//!
//! `d(a, b) = sum w m_a m_b (a - b)^2 / sum w m_a m_b`, and `+inf` when the mutual weight
//! `sum w m_a m_b` is below `min_patch_overlap_fraction * sum w`.
//!
//! The numerator expands into `(w m_a a^2) . m_b + m_a . (w m_b b^2) - 2 (w m_a a) . (m_b b)`,
//! so for all keypoint pairs at once it is one matrix product with inner size `3P`:
//! `[w m_a a^2 | m_a | w m_a a] (N_i x 3P)  x  [m_b ; w m_b b^2 ; -2 m_b b] (3P x N_j)`,
//! and the denominator a second one, `[w m_a] (N_i x P) x [m_b] (P x N_j)`. They go to
//! faer's GEMM in f32 (patches are z-scored, so f32 keeps ~1e-6 relative precision; checked
//! against a brute-force f64 reference in the tests).
//!
//! **Banded patches.** A patch observed in every cell that lies within the field
//! (`PatchShape::is_banded`) has a mask of one on a band of patch rows `[lo, hi)` (all nine
//! rows, or fewer for a keypoint within four rows of an axial end) and zero elsewhere, which
//! need not be multiplied. In the full tier's tunnels a quarter (64 beams) to a half (the
//! forward sensor) of the places a keypoint can take are banded, in the 0.6 m hume pipe with
//! the forward sensor an eighth, in the pipes with 16 beams, whose masks are speckled, none. For a banded query patch `sum w m_a m_b b^2` and `sum w m_a m_b`
//! are the candidate's sums over the query's band, read off per-keypoint prefix sums over
//! patch rows; likewise with the roles exchanged. A pair of banded patches needs only the
//! cross term `(w a) . (-2 b)` from a product (inner size `P` instead of `4P`), a pair with
//! one banded side `2P`. Each side's keypoints are put in order, banded first (the query's
//! grouped by band), so each of the four blocks is one or two GEMMs of contiguous
//! submatrices and the band sums are runs of additions the compiler vectorises; the
//! distances come out in that order and [`Distances`] maps them back to the keypoints.

use std::ops::Range;

use faer::linalg::matmul::matmul;
use faer::{Accum, Mat, MatMut, MatRef, Par};

use super::correspondences;
use super::patches::{CandidatePatches, PatchShape};

/// The candidate factor `[m_b ; w m_b b^2 ; -2 m_b b]` (`3P x N`) of one landmark, its
/// columns in the order banded first ([`Self::keypoint`] maps a column to its keypoint),
/// with each column's band. Built per comparison ([`Self::fill`]) into a buffer reused from
/// comparison to comparison (a fresh 180-230 KB matrix a pair cost a third of the pair's
/// time in page faults and zeroing).
#[derive(Clone, Debug)]
pub struct PatchFactor {
    matrix: Mat<f32>,
    /// Column -> keypoint.
    order: Vec<u32>,
    /// The first `banded` columns are banded.
    banded: usize,
    /// Per column: its patch rows within the field, `[lo, hi)`.
    bands: Vec<(u32, u32)>,
}

impl Default for PatchFactor {
    fn default() -> Self {
        Self {
            matrix: Mat::new(),
            order: Vec::new(),
            banded: 0,
            bands: Vec::new(),
        }
    }
}

impl PatchFactor {
    /// The factor of `cand` (a new buffer; a comparison reuses one with [`Self::fill`]).
    pub fn new(shape: &PatchShape, cand: &CandidatePatches) -> Self {
        let mut factor = Self::default();
        factor.fill(shape, cand);
        factor
    }

    /// Builds the factor of `cand` in this buffer; every entry is written.
    pub fn fill(&mut self, shape: &PatchShape, cand: &CandidatePatches) {
        let (n, p) = (cand.count(), shape.len());
        self.banded = banded_first(cand, &mut self.order);
        self.bands.clear();
        self.bands.extend(self.order.iter().map(|&k| {
            let (lo, hi) = cand.rows_within(shape, k as usize);
            (lo as u32, hi as u32)
        }));
        self.matrix.resize_with(3 * p, n, |_, _| 0.0);
        let mut patch = vec![0.0f32; p];
        for (col, &k) in self.order.iter().enumerate() {
            cand.patch_into(shape, k as usize, &mut patch);
            pulp::Arch::new().dispatch(FillColumn {
                values: &patch,
                weights: &shape.weights,
                column: self.matrix.col_as_slice_mut(col),
                blocks: |b: f32, w: f32| [1.0, w * b * b, -2.0 * b],
            });
        }
    }

    /// Number of keypoints `N` (columns).
    pub fn count(&self) -> usize {
        self.order.len()
    }

    /// The keypoint of column `col`.
    pub fn keypoint(&self, col: usize) -> usize {
        self.order[col] as usize
    }

    /// The matrix, `3P x N`, columns in [`Self::keypoint`]'s order.
    pub fn matrix(&self) -> MatRef<'_, f32> {
        self.matrix.as_ref()
    }
}

/// `cand`'s keypoints into `order`, the banded ones first, each group in the keypoints'
/// order; returns how many are banded.
fn banded_first(cand: &CandidatePatches, order: &mut Vec<u32>) -> usize {
    let n = cand.count() as u32;
    order.clear();
    order.extend((0..n).filter(|&k| cand.is_banded(k as usize)));
    let banded = order.len();
    order.extend((0..n).filter(|&k| !cand.is_banded(k as usize)));
    banded
}

/// The `R + 1` prefix sums over a patch's rows of `square` (`w m v^2`, flat, `P`) and of the
/// weights where `mask` (`m`, 1 or 0) is set, into `square_out` and `weight_out`: eight
/// lanes of partial sums, which the compiler vectorises where this is inlined into
/// [`pulp`]-dispatched code ([`BandSums`]).
#[inline(always)]
fn prefix_sums(
    shape: &PatchShape,
    mask: &[f32],
    square: &[f32],
    square_out: &mut [f32],
    weight_out: &mut [f32],
) {
    let pc = shape.cols;
    let (mut sq, mut w) = (0.0f32, 0.0f32);
    square_out[0] = 0.0;
    weight_out[0] = 0.0;
    for r in 0..shape.rows {
        let span = r * pc..(r + 1) * pc;
        sq += lane_sum(&square[span.clone()], |_, v| v);
        w += lane_sum(&mask[span.clone()], |k, m| {
            m * shape.weights[span.start + k]
        });
        square_out[r + 1] = sq;
        weight_out[r + 1] = w;
    }
}

/// `sum f(k, x[k])` over eight lanes of partial sums.
#[inline(always)]
fn lane_sum(x: &[f32], f: impl Fn(usize, f32) -> f32) -> f32 {
    let mut lanes = [0.0f32; 8];
    let chunks = x.chunks_exact(8);
    let tail = chunks.remainder();
    for (c, chunk) in chunks.enumerate() {
        for (l, (lane, &v)) in lanes.iter_mut().zip(chunk).enumerate() {
            *lane += f(8 * c + l, v);
        }
    }
    let head = x.len() - tail.len();
    let mut total = lanes.iter().sum::<f32>();
    for (k, &v) in tail.iter().enumerate() {
        total += f(head + k, v);
    }
    total
}

/// One keypoint's column of a factor, three blocks of `P` from its patch `values` and the
/// weights: `blocks(v, w)` gives a cell's three entries (the candidate's `[1, w b^2, -2 b]`,
/// the query's transposed `[w a^2, 1, w a]`), an unobserved cell's (NaN) masked to +0 bit by
/// bit, as the zeros the factors were once initialised with. Branch-free, so that the
/// compiler vectorises it at the CPU's width under [`pulp`] dispatch, as [`Ratio`].
struct FillColumn<'a, F> {
    values: &'a [f32],
    weights: &'a [f32],
    column: &'a mut [f32],
    blocks: F,
}

impl<F: Fn(f32, f32) -> [f32; 3]> pulp::WithSimd for FillColumn<'_, F> {
    type Output = ();

    #[inline(always)]
    fn with_simd<S: pulp::Simd>(self, _simd: S) {
        let p = self.weights.len();
        let (first, rest) = self.column.split_at_mut(p);
        let (second, third) = rest.split_at_mut(p);
        let cells = self.values.iter().zip(self.weights);
        let out = first
            .iter_mut()
            .zip(second.iter_mut())
            .zip(third.iter_mut());
        for ((&v, &w), ((x, y), z)) in cells.zip(out) {
            let keep = 0u32.wrapping_sub(u32::from(!v.is_nan()));
            let entries = (self.blocks)(v, w);
            *x = f32::from_bits(entries[0].to_bits() & keep);
            *y = f32::from_bits(entries[1].to_bits() & keep);
            *z = f32::from_bits(entries[2].to_bits() & keep);
        }
    }
}

/// Banded query rows `start..end` that share the band `[lo, hi)`.
#[derive(Clone, Copy, Debug, PartialEq)]
struct BandRun {
    start: usize,
    end: usize,
    lo: usize,
    hi: usize,
}

/// The query factors of one landmark under one heading, its rows in the order banded first
/// (grouped by band), then the rest ([`Self::keypoint`]): `[w m_a a^2 | m_a | w m_a a]`
/// (`N x 3P`, numerator), `[w m_a]` for the rows that are not banded (denominator), and
/// every row's prefix sums over the patch rows. Built from the landmark's patches
/// ([`CandidatePatches`]); `flipped` reverses each patch (heading 180°).
#[derive(Clone, Debug)]
pub struct QueryPatches {
    /// `N x 3P`.
    numerator: Mat<f32>,
    /// `(N - banded) x P`.
    denominator: Mat<f32>,
    /// Row -> keypoint.
    order: Vec<u32>,
    /// The first `banded` rows are banded.
    banded: usize,
    /// The banded rows by band.
    runs: Vec<BandRun>,
    /// `(R + 1) x N`, row-major: prefix sum `r` of every row's `w m_a a^2` at `r * N`.
    prefix_square: Vec<f32>,
    /// The same for `w m_a`.
    prefix_weight: Vec<f32>,
}

impl QueryPatches {
    /// Rearranges a landmark's candidate patches into query factors.
    pub fn from_candidate(shape: &PatchShape, cand: &CandidatePatches, flipped: bool) -> Self {
        let (n, p, r1) = (cand.count(), shape.len(), shape.rows + 1);
        let band = |k: usize| {
            let (lo, hi) = cand.rows_within(shape, k);
            if flipped {
                (shape.rows - hi, shape.rows - lo)
            } else {
                (lo, hi)
            }
        };
        let mut order = Vec::new();
        let banded = banded_first(cand, &mut order);
        order[..banded].sort_by_key(|&k| band(k as usize));
        let mut runs: Vec<BandRun> = Vec::new();
        for (row, &k) in order[..banded].iter().enumerate() {
            let (lo, hi) = band(k as usize);
            match runs.last_mut() {
                Some(run) if (run.lo, run.hi) == (lo, hi) => run.end = row + 1,
                _ => runs.push(BandRun {
                    start: row,
                    end: row + 1,
                    lo,
                    hi,
                }),
            }
        }
        let mut numerator_t = Mat::<f32>::zeros(3 * p, n);
        let mut denominator_t = Mat::<f32>::zeros(p, n - banded);
        let (mut prefix_square, mut prefix_weight) = (vec![0.0f32; r1 * n], vec![0.0f32; r1 * n]);
        let mut values = vec![0.0f32; p];
        let (mut square, mut weight) = (vec![0.0; r1], vec![0.0; r1]);
        for (row, &k) in order.iter().enumerate() {
            cand.patch_into(shape, k as usize, &mut values);
            if flipped {
                // The reversed patch; the weights are symmetric.
                values.reverse();
            }
            let column = numerator_t.col_as_slice_mut(row);
            pulp::Arch::new().dispatch(FillColumn {
                values: &values,
                weights: &shape.weights,
                column,
                blocks: |a: f32, w: f32| [w * a * a, 1.0, w * a],
            });
            let column = numerator_t.col_as_slice(row);
            if row >= banded {
                let den = denominator_t.col_as_slice_mut(row - banded);
                for ((d, &m), &w) in den.iter_mut().zip(&column[p..2 * p]).zip(&shape.weights) {
                    *d = m * w;
                }
            }
            prefix_sums(
                shape,
                &column[p..2 * p],
                &column[..p],
                &mut square,
                &mut weight,
            );
            for r in 0..r1 {
                prefix_square[r * n + row] = square[r];
                prefix_weight[r * n + row] = weight[r];
            }
        }
        // Built transposed (a keypoint's row is a contiguous column, written in one pass),
        // kept column-major: faer's GEMM ran a pair about 15 % slower on the transposed view.
        Self {
            numerator: numerator_t.transpose().to_owned(),
            denominator: denominator_t.transpose().to_owned(),
            order,
            banded,
            runs,
            prefix_square,
            prefix_weight,
        }
    }

    /// Number of keypoints `N` (rows).
    pub fn count(&self) -> usize {
        self.order.len()
    }

    /// The keypoint of row `row`.
    pub fn keypoint(&self, row: usize) -> usize {
        self.order[row] as usize
    }
}

/// The patch distances of a landmark pair, `+inf` where the mutually observed weight is too
/// small, in the factors' orders ([`QueryPatches::keypoint`], [`PatchFactor::keypoint`]).
#[derive(Debug)]
pub struct Distances<'a> {
    matrix: Mat<f32>,
    query: &'a QueryPatches,
    candidate: &'a PatchFactor,
}

impl Distances<'_> {
    /// The unique mutual nearest keypoint pairs (`correspondences::mutual_nearest`), as
    /// `(query keypoint, candidate keypoint)`, in the query keypoints' order.
    pub fn mutual_nearest(&self) -> Vec<(usize, usize)> {
        let mut pairs: Vec<(usize, usize)> = correspondences::mutual_nearest(&self.matrix)
            .into_iter()
            .map(|(i, j)| (self.query.keypoint(i), self.candidate.keypoint(j)))
            .collect();
        pairs.sort_unstable();
        pairs
    }

    /// The distance between query keypoint `i` and candidate keypoint `j` (tests, one-off
    /// look-ups: it searches the orders).
    pub fn get(&self, i: usize, j: usize) -> Option<f32> {
        let row = self.query.order.iter().position(|&k| k as usize == i)?;
        let col = self.candidate.order.iter().position(|&k| k as usize == j)?;
        Some(self.matrix[(row, col)])
    }
}

/// All patch distances between the query's and the candidate's keypoints: the four blocks'
/// GEMMs (banded or not, on either side), the band sums, then the division.
pub fn distances<'a>(
    shape: &PatchShape,
    query: &'a QueryPatches,
    cand: &'a PatchFactor,
    min_overlap: f64,
) -> Distances<'a> {
    let (ni, nj, p) = (query.count(), cand.count(), shape.len());
    let mut num = Mat::<f32>::zeros(ni, nj);
    let mut den = Mat::<f32>::zeros(ni, nj);
    if ni > 0 && nj > 0 {
        products(query, cand, p, &mut num, &mut den);
        pulp::Arch::new().dispatch(BandSums {
            shape,
            query,
            cand,
            num: &mut num,
            den: &mut den,
        });
        let min_weight = (min_overlap * shape.weight_sum) as f32;
        pulp::Arch::new().dispatch(Ratio {
            num: &mut num,
            den: &den,
            min_weight,
        });
    }
    Distances {
        matrix: num,
        query,
        candidate: cand,
    }
}

/// The matrix products of [`distances`], block by block (`b`: banded, `p`: not): `bb` the
/// cross term only; `bp` `[w a^2 | . | w a] x [m_b ; . ; -2 m_b b]` (two GEMMs); `pb`
/// `[m_a | w m_a a] x [w b^2 ; -2 b]`; `pp` every term and the denominator.
fn products(q: &QueryPatches, c: &PatchFactor, p: usize, num: &mut Mat<f32>, den: &mut Mat<f32>) {
    let (ni, nj) = (q.count(), c.count());
    let (qb, cb) = (q.banded, c.banded);
    let (qa, ca) = (q.numerator.as_ref(), c.matrix.as_ref());
    let gemm = |dst: MatMut<'_, f32>, lhs: MatRef<'_, f32>, rhs: MatRef<'_, f32>, accum| {
        if dst.nrows() > 0 && dst.ncols() > 0 {
            matmul(dst, accum, lhs, rhs, 1.0f32, Par::Seq);
        }
    };
    let (top, bottom) = (0..qb, qb..ni);
    let (left, right) = (0..cb, cb..nj);
    let rows =
        |r: &Range<usize>, from: usize, len: usize| qa.submatrix(r.start, from, r.len(), len);
    let cols =
        |c: &Range<usize>, from: usize, len: usize| ca.submatrix(from, c.start, len, c.len());
    fn block<'m>(m: MatMut<'m, f32>, r: &Range<usize>, c: &Range<usize>) -> MatMut<'m, f32> {
        m.submatrix_mut(r.start, c.start, r.len(), c.len())
    }
    // (query rows, candidate columns, the inner range both factors share, accumulate).
    let terms = [
        (&top, &left, 2 * p, p, Accum::Replace), // bb: (w a) . (-2 b)
        (&top, &right, 0, p, Accum::Replace),    // bp: (w a^2) . m_b
        (&top, &right, 2 * p, p, Accum::Add),    //     + (w a) . (-2 m_b b)
        (&bottom, &left, p, 2 * p, Accum::Replace), // pb
        (&bottom, &right, 0, 3 * p, Accum::Replace), // pp
    ];
    for (r, c, from, len, accum) in terms {
        gemm(
            block(num.as_mut(), r, c),
            rows(r, from, len),
            cols(c, from, len),
            accum,
        );
    }
    gemm(
        block(den.as_mut(), &bottom, &right),
        q.denominator.as_ref(),
        cols(&right, 0, p),
        Accum::Replace,
    );
}

/// The band sums of [`distances`]: for a banded candidate column the query rows' own sums
/// over its band (contiguous, from the transposed prefix sums), and for every column the
/// candidate's sums over each banded run of query rows (its prefix sums from its factor's
/// column, when the query has banded rows).
struct BandSums<'a> {
    shape: &'a PatchShape,
    query: &'a QueryPatches,
    cand: &'a PatchFactor,
    num: &'a mut Mat<f32>,
    den: &'a mut Mat<f32>,
}

impl<'a> pulp::WithSimd for BandSums<'a> {
    type Output = ();

    #[inline(always)]
    fn with_simd<S: pulp::Simd>(self, _simd: S) {
        let (q, c) = (self.query, self.cand);
        let r1 = self.shape.rows + 1;
        let (mut square, mut weight) = (vec![0.0f32; r1], vec![0.0f32; r1]);
        for j in 0..c.count() {
            let (num, den) = (self.num.col_as_slice_mut(j), self.den.col_as_slice_mut(j));
            if j < c.banded {
                // Prefix sum `r` of every query row at `r * N` (transposed).
                let n = num.len();
                let at = |sums: &'a [f32], r: usize| &sums[r * n..(r + 1) * n];
                let (lo, hi) = (c.bands[j].0 as usize, c.bands[j].1 as usize);
                let square = at(&q.prefix_square, hi)
                    .iter()
                    .zip(at(&q.prefix_square, lo));
                for (x, (h, l)) in num.iter_mut().zip(square) {
                    *x += h - l;
                }
                let weight = at(&q.prefix_weight, hi)
                    .iter()
                    .zip(at(&q.prefix_weight, lo));
                for (x, (h, l)) in den.iter_mut().zip(weight) {
                    *x = h - l;
                }
            }
            if q.runs.is_empty() {
                continue;
            }
            let column = c.matrix.col_as_slice(j);
            let p = column.len() / 3;
            prefix_sums(
                self.shape,
                &column[..p],
                &column[p..2 * p],
                &mut square,
                &mut weight,
            );
            for run in &q.runs {
                let s = square[run.hi] - square[run.lo];
                for n in &mut num[run.start..run.end] {
                    *n += s;
                }
                if j >= c.banded {
                    let w = weight[run.hi] - weight[run.lo];
                    den[run.start..run.end].fill(w);
                }
            }
        }
    }
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
