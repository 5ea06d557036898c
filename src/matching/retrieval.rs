//! Coarse retrieval (not in the paper, whose database holds 20 candidates): a compact,
//! heading-invariant summary of each normalised field that hands the exact matcher (patches,
//! mutual nearest neighbours, verification) a short list.
//!
//! **Signature.** The normalised field (Eq. 2 residual, after the `p` smoothing) pooled into
//! blocks of `BLOCK_ROWS x BLOCK_COLS` cells, two channels per block: the mean offset (where
//! the texture bulges or recedes) and the RMS offset (where the texture is strong: chips,
//! groove irregularities, the features keypoints land on). Each row of blocks is standardised
//! (the axial energy profile every joint shares would make all signatures alike), then each
//! channel is scaled to unit norm over the observed blocks (unobserved blocks are 0) and the
//! two are concatenated with equal weight: a signature is a unit vector and the similarity of
//! two is one dot product. The tunnel and pipe grids (16 x 256) give 8 x 16 blocks: 256
//! values, kept as `i8` in the database's [`CoarseIndex`] (260 bytes per landmark).
//!
//! **Headings and shifts.** Reversal (paper §III-B) is the 180° rotation of the grid
//! ([`super::heading`]); a query's signatures are taken under both headings, from the
//! flipped field itself (exact for any grid), and at the axial shifts [`QUERY_SHIFTS`] (two
//! sessions detect a boundary's origin a few rows apart). The similarity is the best over
//! them, so the ranking is invariant to the direction of travel; database entries keep one
//! (forward, unshifted) signature.
//!
//! **Why pooled fields, not an index over keypoint patches.** The exact matcher already pays
//! a GEMM per candidate over all patches; an inverted index over quantised patches would need a
//! codebook trained per corridor, and the patches of identical texture at another position of
//! the circumference (a shifted gravity reference) would vote anyway. The pooled field is a
//! few integer dot products per candidate on 256 bytes, and the blocks (16 columns = 22°,
//! 2 rows) absorb the sub-cell misalignment and gravity errors of a revisit (8-column blocks
//! gave the same short-list hits on the simulated re-inspection at twice the scan cost).
//! Measured (`matching::tests::coarse_short_list_keeps_the_exhaustive_top1`,
//! `tests/test_survey.py` and the `retrieval` bench): see
//! `MatchingConfig::retrieval_short_list`.

use super::heading::flip_grid;

/// Rows of the descriptor pooled into one block.
pub const BLOCK_ROWS: usize = 2;
/// Columns of the descriptor pooled into one block.
pub const BLOCK_COLS: usize = 16;

/// Block-grid size of a `rows x cols` descriptor (partial blocks at the ends count).
pub fn block_grid(rows: usize, cols: usize) -> (usize, usize) {
    (rows.div_ceil(BLOCK_ROWS), cols.div_ceil(BLOCK_COLS))
}

/// Length of a signature of a `rows x cols` descriptor.
pub fn signature_len(rows: usize, cols: usize) -> usize {
    let (br, bc) = block_grid(rows, cols);
    2 * br * bc
}

/// Centres and scales one channel to unit norm over the observed blocks (in place); an
/// all-zero or unobserved channel stays zero.
fn unit_channel(values: &mut [f32], observed: &[bool]) {
    let n = observed.iter().filter(|&&o| o).count();
    if n == 0 {
        values.iter_mut().for_each(|v| *v = 0.0);
        return;
    }
    let mean = values
        .iter()
        .zip(observed)
        .filter(|(_, o)| **o)
        .map(|(v, _)| f64::from(*v))
        .sum::<f64>()
        / n as f64;
    let mut norm = 0.0f64;
    for (v, &o) in values.iter_mut().zip(observed) {
        *v = if o {
            (f64::from(*v) - mean) as f32
        } else {
            0.0
        };
        norm += f64::from(*v) * f64::from(*v);
    }
    if norm > 0.0 {
        let scale = (1.0 / (2.0 * norm).sqrt()) as f32;
        values.iter_mut().for_each(|v| *v *= scale);
    }
}

/// Standardises each row of blocks (`bc` blocks) over its observed blocks: subtracts the
/// row's mean and divides by its standard deviation, so the axial profile that every
/// boundary shares (the joint's row holds most of the texture energy in every descriptor)
/// does not make all signatures alike.
fn standardise_rows(values: &mut [f32], observed: &[bool], bc: usize) {
    for (row, seen) in values.chunks_mut(bc).zip(observed.chunks(bc)) {
        let vals: Vec<f64> = row
            .iter()
            .zip(seen)
            .filter(|(_, o)| **o)
            .map(|(v, _)| f64::from(*v))
            .collect();
        if vals.len() < 2 {
            row.iter_mut().for_each(|v| *v = 0.0);
            continue;
        }
        let mean = vals.iter().sum::<f64>() / vals.len() as f64;
        let var = vals.iter().map(|v| (v - mean) * (v - mean)).sum::<f64>() / vals.len() as f64;
        let scale = if var > 0.0 { 1.0 / var.sqrt() } else { 0.0 };
        for (v, &o) in row.iter_mut().zip(seen) {
            *v = if o {
                ((f64::from(*v) - mean) * scale) as f32
            } else {
                0.0
            };
        }
    }
}

/// The signature of a normalised field (`rows x cols` row-major, module docs).
pub fn signature(field: &[f64], observed: &[bool], rows: usize, cols: usize) -> Vec<f32> {
    let (br, bc) = block_grid(rows, cols);
    let blocks = br * bc;
    let mut sum = vec![0.0f64; blocks];
    let mut sq = vec![0.0f64; blocks];
    let mut count = vec![0usize; blocks];
    for r in 0..rows {
        for c in 0..cols {
            let i = r * cols + c;
            if observed.get(i).copied().unwrap_or(false) {
                let v = field.get(i).copied().unwrap_or(0.0);
                let b = (r / BLOCK_ROWS) * bc + c / BLOCK_COLS;
                sum[b] += v;
                sq[b] += v * v;
                count[b] += 1;
            }
        }
    }
    // A block counts as observed when at least half its cells are.
    let full = BLOCK_ROWS * BLOCK_COLS;
    let seen: Vec<bool> = count.iter().map(|&n| 2 * n >= full).collect();
    let mut mean: Vec<f32> = (0..blocks)
        .map(|b| (sum[b] / count[b].max(1) as f64) as f32)
        .collect();
    let mut rms: Vec<f32> = (0..blocks)
        .map(|b| (sq[b] / count[b].max(1) as f64).sqrt() as f32)
        .collect();
    standardise_rows(&mut mean, &seen, bc);
    standardise_rows(&mut rms, &seen, bc);
    unit_channel(&mut mean, &seen);
    unit_channel(&mut rms, &seen);
    mean.extend(rms);
    mean
}

/// Signatures under both headings: `[forward, reversed]`.
pub fn signatures(field: &[f64], observed: &[bool], rows: usize, cols: usize) -> [Vec<f32>; 2] {
    let forward = signature(field, observed, rows, cols);
    let reversed = signature(&flip_grid(field), &flip_grid(observed), rows, cols);
    [forward, reversed]
}

/// Dot product (f32 lanes, summed in blocks of 8 so the compiler vectorises it).
#[inline]
pub fn dot(a: &[f32], b: &[f32]) -> f32 {
    let mut acc = [0.0f32; 8];
    let (ca, cb) = (a.chunks_exact(8), b.chunks_exact(8));
    let (ra, rb) = (ca.remainder(), cb.remainder());
    for (x, y) in ca.zip(cb) {
        for k in 0..8 {
            acc[k] += x[k] * y[k];
        }
    }
    let tail: f32 = ra.iter().zip(rb).map(|(x, y)| x * y).sum();
    acc.iter().sum::<f32>() + tail
}

/// Axial shifts (rows) a query's signature is also taken at: a boundary's origin is
/// detected a few centimetres apart in two sessions (2-3 rows of the pipe grid), more than
/// a block absorbs. On the simulated hume pipe the two exhaustive Top-1s the unshifted
/// signatures missed were 2 and 3 rows off.
pub const QUERY_SHIFTS: [isize; 3] = [0, -2, 2];

/// A row-major grid moved by `shift` rows (`out[r] = grid[r + shift]`), `fill` outside.
fn shifted<T: Copy>(grid: &[T], rows: usize, cols: usize, shift: isize, fill: T) -> Vec<T> {
    let mut out = vec![fill; rows * cols];
    for r in 0..rows {
        let src = r as isize + shift;
        if src >= 0 && (src as usize) < rows {
            let s = src as usize * cols;
            out[r * cols..(r + 1) * cols].copy_from_slice(&grid[s..s + cols]);
        }
    }
    out
}

/// A query's signatures: both headings at every shift of [`QUERY_SHIFTS`] (the first is the
/// forward, unshifted one: the signature a database entry keeps).
pub fn query_signatures(
    field: &[f64],
    observed: &[bool],
    rows: usize,
    cols: usize,
) -> Vec<Vec<f32>> {
    let flipped = (flip_grid(field), flip_grid(observed));
    let mut out = Vec::with_capacity(2 * QUERY_SHIFTS.len());
    for (f, o) in [(field, observed), (&flipped.0[..], &flipped.1[..])] {
        for &s in &QUERY_SHIFTS {
            let (fs, os) = (
                shifted(f, rows, cols, s, 0.0),
                shifted(o, rows, cols, s, false),
            );
            out.push(signature(&fs, &os, rows, cols));
        }
    }
    out
}

/// Heading-invariant similarity of a query (its signatures) and a candidate (forward): the
/// best over the query's signatures.
#[inline]
pub fn similarity(query: &[Vec<f32>], candidate: &[f32]) -> f32 {
    query
        .iter()
        .map(|q| dot(q, candidate))
        .fold(f32::NEG_INFINITY, f32::max)
}

/// A signature quantised to `i8` with one scale (`value ~ q * scale`): 127 levels of its
/// largest magnitude keep a unit vector's dot products to about 1e-3.
pub fn quantise(signature: &[f32]) -> (Vec<i8>, f32) {
    let largest = signature.iter().fold(0.0f32, |m, v| m.max(v.abs()));
    let scale = if largest > 0.0 { largest / 127.0 } else { 1.0 };
    let q = signature
        .iter()
        .map(|v| (v / scale).round().clamp(-127.0, 127.0) as i8)
        .collect();
    (q, scale)
}

/// Integer dot product of two `i8` vectors: pairs of `i16` products summed into 16 `i32`
/// lanes, the pattern the compiler turns into packed multiply-adds (`pmaddwd`; AVX2 or
/// AVX-512 under [`pulp`] dispatch, see [`CoarseIndex::short_list`]). Exact: at most
/// `dim * 127^2` per lane.
#[inline(always)]
fn dot_i8(a: &[i8], b: &[i8]) -> i32 {
    let mut acc = [0i32; 16];
    let n = a.len().min(b.len());
    let whole = n - n % 32;
    let (ca, cb) = (&a[..whole], &b[..whole]);
    let mut start = 0;
    while start < whole {
        let (x, y) = (&ca[start..start + 32], &cb[start..start + 32]);
        for k in 0..16 {
            acc[k] += i32::from(x[2 * k]) * i32::from(y[2 * k])
                + i32::from(x[2 * k + 1]) * i32::from(y[2 * k + 1]);
        }
        start += 32;
    }
    let mut total = 0;
    for k in 0..16 {
        total += acc[k];
    }
    for k in whole..n {
        total += i32::from(a[k]) * i32::from(b[k]);
    }
    total
}

/// A query's signatures quantised for the scan ([`quantise`]), in one array (signature `k`
/// = `values[k * dim..]`, scale `scales[k]`). A prepared view keeps its signatures in this
/// form only ([`crate::matching::PreparedLandmark::coarse`]): the scan and the database's
/// index read nothing else, and six signatures take 1.5 KB instead of the f32 ones' 6 KB.
#[derive(Clone, Debug, Default)]
pub struct QuantisedQuery {
    dim: usize,
    values: Vec<i8>,
    scales: Vec<f32>,
}

impl QuantisedQuery {
    /// Quantises every signature of a query (all of one length: those of a shorter or
    /// longer one are left out).
    pub fn new(signatures: &[Vec<f32>]) -> Self {
        let dim = signatures.first().map_or(0, Vec::len);
        let mut out = Self {
            dim,
            values: Vec::with_capacity(dim * signatures.len()),
            scales: Vec::with_capacity(signatures.len()),
        };
        for (q, scale) in signatures
            .iter()
            .filter(|s| s.len() == dim)
            .map(|s| quantise(s))
        {
            out.values.extend(q);
            out.scales.push(scale);
        }
        out
    }

    /// Number of signatures.
    pub fn len(&self) -> usize {
        self.scales.len()
    }

    /// True when there is none.
    pub fn is_empty(&self) -> bool {
        self.scales.is_empty()
    }

    /// The first signature (the forward, unshifted one a database entry is indexed by) and its
    /// scale.
    pub fn first(&self) -> Option<(&[i8], f32)> {
        Some((self.values.get(..self.dim)?, *self.scales.first()?))
    }

    /// Heap bytes held.
    pub fn heap_bytes(&self) -> usize {
        self.values.capacity() + 4 * self.scales.capacity()
    }

    /// Similarity to one quantised row: the best over the query's signatures (plain loops,
    /// inlined into the dispatched scan: an iterator fold there was compiled out of line for
    /// baseline x86-64).
    #[inline(always)]
    fn similarity(&self, row: &[i8], scale: f32) -> f32 {
        let mut best = f32::NEG_INFINITY;
        if self.dim > 0 {
            for (q, s) in self.values.chunks_exact(self.dim).zip(&self.scales) {
                best = f32::max(best, dot_i8(q, row) as f32 * s);
            }
        }
        best * scale
    }
}

/// Signatures of many landmarks in one contiguous array (row `k` = landmark `k`), quantised
/// to `i8` with one scale per row ([`quantise`]), as are the query's: the scan is integer
/// multiply-adds over a quarter of the bytes of f32 rows (which took 1.9 ms for 10,000 with
/// two query signatures on a loaded 2-core machine, `retrieval` bench). The ranking only
/// needs the order of the similarities.
#[derive(Clone, Debug, Default)]
pub struct CoarseIndex {
    dim: usize,
    values: Vec<i8>,
    scales: Vec<f32>,
}

impl CoarseIndex {
    /// Appends one signature; all must share a length (the database checks grids first).
    pub fn push(&mut self, signature: &[f32]) {
        let (q, scale) = quantise(signature);
        self.push_quantised(&q, scale);
    }

    /// Appends the first signature of a prepared view ([`QuantisedQuery::first`]; an empty
    /// row if it has none), the values [`Self::push`] would have quantised.
    pub fn push_first(&mut self, view: &QuantisedQuery) {
        let (q, scale) = view.first().unwrap_or((&[], 1.0));
        self.push_quantised(q, scale);
    }

    fn push_quantised(&mut self, q: &[i8], scale: f32) {
        if self.scales.is_empty() {
            self.dim = q.len();
        }
        if q.len() == self.dim {
            self.values.extend_from_slice(q);
        } else {
            // Unreachable through the database (one grid); keep rows aligned regardless.
            self.values.extend((0..self.dim).map(|_| 0i8));
        }
        self.scales.push(scale);
    }

    /// Number of signatures.
    pub fn len(&self) -> usize {
        self.scales.len()
    }

    /// True when empty.
    pub fn is_empty(&self) -> bool {
        self.scales.is_empty()
    }

    /// Bytes held per landmark.
    pub fn bytes_per_landmark(&self) -> usize {
        self.dim + std::mem::size_of::<f32>()
    }

    /// Similarity of `query` (its signatures) to signature `k` (0 if out of range).
    pub fn similarity(&self, query: &[Vec<f32>], k: usize) -> f32 {
        self.similarity_quantised(&QuantisedQuery::new(query), k)
    }

    #[inline(always)]
    fn similarity_quantised(&self, query: &QuantisedQuery, k: usize) -> f32 {
        match (
            self.values.get(k * self.dim..(k + 1) * self.dim),
            self.scales.get(k),
        ) {
            (Some(row), Some(&scale)) => query.similarity(row, scale),
            _ => 0.0,
        }
    }

    /// The `length` candidates among `indices` most similar to `query` (both headings), best
    /// first; ties by index. `parallel`: rayon over chunks of the candidates.
    pub fn short_list(
        &self,
        query: &QuantisedQuery,
        indices: &[usize],
        length: usize,
        parallel: bool,
    ) -> Vec<usize> {
        use rayon::prelude::*;
        let scan = |chunk: &[usize]| {
            pulp::Arch::new().dispatch(Scan {
                index: self,
                query,
                indices: chunk,
            })
        };
        let mut scored: Vec<(f32, usize)> = if parallel {
            indices.par_chunks(1024).flat_map_iter(scan).collect()
        } else {
            scan(indices)
        };
        let length = length.min(scored.len());
        if length == 0 {
            return Vec::new();
        }
        let order = |a: &(f32, usize), b: &(f32, usize)| b.0.total_cmp(&a.0).then(a.1.cmp(&b.1));
        if length < scored.len() {
            scored.select_nth_unstable_by(length - 1, order);
            scored.truncate(length);
        }
        scored.sort_unstable_by(order);
        scored.into_iter().map(|(_, k)| k).collect()
    }
}

/// The coarse scores of some rows of an index, compiled for the best instruction set the
/// CPU has ([`pulp::Arch::dispatch`]): the integer dot products vectorise 2-4x wider than
/// on baseline x86-64. Scores are exact integers scaled as in [`QuantisedQuery`], so every
/// instruction set ranks identically.
struct Scan<'a> {
    index: &'a CoarseIndex,
    query: &'a QuantisedQuery,
    indices: &'a [usize],
}

impl pulp::WithSimd for Scan<'_> {
    type Output = Vec<(f32, usize)>;

    #[inline(always)]
    fn with_simd<S: pulp::Simd>(self, _simd: S) -> Self::Output {
        let mut out = Vec::with_capacity(self.indices.len());
        for &k in self.indices {
            out.push((self.index.similarity_quantised(self.query, k), k));
        }
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn field(rows: usize, cols: usize, seed: u64) -> Vec<f64> {
        let mut rng = crate::matching::synthetic::Rng::new(seed);
        (0..rows * cols).map(|_| rng.normal()).collect()
    }

    #[test]
    fn signatures_are_unit_vectors_and_heading_invariant() {
        let (rows, cols) = (16, 256);
        let f = field(rows, cols, 3);
        let observed: Vec<bool> = (0..rows * cols).map(|i| i % 256 > 40).collect();
        let [fwd, rev] = signatures(&f, &observed, rows, cols);
        assert_eq!(fwd.len(), signature_len(rows, cols));
        assert!((dot(&fwd, &fwd) - 1.0).abs() < 1e-4);
        // The same surface seen in the other direction: its forward signature is this one's
        // reversed signature, so the similarity is the self-similarity.
        let flipped = signatures(&flip_grid(&f), &flip_grid(&observed), rows, cols);
        assert!((similarity(&flipped, &fwd) - 1.0).abs() < 1e-4);
        // ... and the query signatures find it under the heading flip and a 2-row shift.
        let moved = shifted(&flip_grid(&f), rows, cols, 2, 0.0);
        let moved_obs = shifted(&flip_grid(&observed), rows, cols, 2, false);
        let q = query_signatures(&moved, &moved_obs, rows, cols);
        assert!(similarity(&q, &fwd) > 0.8, "{}", similarity(&q, &fwd));
        assert!((dot(&flipped[0], &rev) - 1.0).abs() < 1e-4);
        // An unrelated field is far less similar.
        let other = signature(&field(rows, cols, 4), &observed, rows, cols);
        assert!(similarity(&[fwd.clone(), rev], &other) < 0.5);
    }

    #[test]
    fn short_list_matches_a_brute_force_sort() {
        let (rows, cols) = (16, 64);
        let observed = vec![true; rows * cols];
        let mut index = CoarseIndex::default();
        for k in 0..300 {
            index.push(&signature(&field(rows, cols, k), &observed, rows, cols));
        }
        let q = signatures(&field(rows, cols, 7), &observed, rows, cols).to_vec();
        let all: Vec<usize> = (0..300).filter(|k| k % 3 != 0).collect();
        let mut brute: Vec<(f32, usize)> =
            all.iter().map(|&k| (index.similarity(&q, k), k)).collect();
        brute.sort_by(|a, b| b.0.total_cmp(&a.0).then(a.1.cmp(&b.1)));
        let expected: Vec<usize> = brute.iter().take(10).map(|x| x.1).collect();
        let quantised = QuantisedQuery::new(&q);
        assert_eq!(index.short_list(&quantised, &all, 10, false), expected);
        assert_eq!(index.short_list(&quantised, &all, 10, true), expected);
        assert_eq!(
            index.short_list(&quantised, &all, 1000, false).len(),
            all.len()
        );
        assert_eq!(index.short_list(&quantised, &all, 10, false)[0], 7);
        // An index built from views' quantised signatures (what the database keeps) holds the
        // rows the f32 signatures give, so it ranks alike.
        let mut from_views = CoarseIndex::default();
        for k in 0..300 {
            let view =
                QuantisedQuery::new(&[signature(&field(rows, cols, k), &observed, rows, cols)]);
            from_views.push_first(&view);
        }
        assert_eq!(
            (&from_views.values, &from_views.scales),
            (&index.values, &index.scales)
        );
        assert_eq!(from_views.short_list(&quantised, &all, 10, true), expected);
        assert_eq!(quantised.len(), 2);
        assert_eq!(
            quantised.first().map(|(v, _)| v.len()),
            Some(signature_len(rows, cols))
        );
        // Quantisation keeps the similarities to about 1e-3.
        let exact = signature(&field(rows, cols, 11), &observed, rows, cols);
        assert!((index.similarity(&q, 11) - similarity(&q, &exact)).abs() < 5e-3);
        assert!((index.similarity(&q, 7) - 1.0).abs() < 5e-3);
    }
}
