//! Coarse retrieval (not in the paper, whose database holds 20 candidates): a compact,
//! heading-invariant summary of each normalised field that hands the exact matcher (patches,
//! mutual nearest neighbours, verification) a short list.
//!
//! **Signature.** The normalised field (Eq. 2 residual, after the `p` smoothing) pooled into
//! `BLOCK_ROWS x BLOCK_COLS` cells per block, two channels per block: the mean offset (where
//! the texture bulges or recedes) and the RMS offset (where the texture is strong: chips,
//! groove irregularities, the features keypoints land on). Each channel is centred and scaled
//! to unit norm over the observed blocks (unobserved blocks are 0), and the two are
//! concatenated with equal weight, so a signature is a unit vector and the similarity of two
//! is one dot product. The tunnel and pipe grids (16 x 256) give 8 x 32 blocks: 512 values,
//! kept as `i8` in the database's [`CoarseIndex`] (516 bytes per landmark).
//!
//! **Headings.** Reversal (paper §III-B) is the 180° rotation of the grid ([`super::heading`]);
//! each prepared landmark keeps its signature under both headings, computed from the flipped
//! field itself (exact for any grid, not only for block sizes that divide it). The similarity
//! of a query and a candidate is the larger of the two headings' dot products, so the ranking
//! is invariant to the direction of travel.
//!
//! **Why pooled fields, not an index over keypoint patches.** The exact matcher already pays
//! a GEMM per candidate over all patches; an inverted index over quantised patches would need a
//! codebook trained per corridor, and the patches of identical texture at another position of
//! the circumference (a shifted gravity reference) would vote anyway. The pooled field is one
//! streaming dot product per candidate (memory bound: half a KiB per landmark), and the
//! blocks (8 columns = 11°, 2 rows) absorb the sub-cell misalignment and gravity errors of a
//! revisit. Measured (`matching::tests::coarse_short_list_keeps_the_exhaustive_top1` and the
//! `retrieval` bench): see `MatchingConfig::retrieval_short_list`.

use super::heading::flip_grid;

/// Rows of the descriptor pooled into one block.
pub const BLOCK_ROWS: usize = 2;
/// Columns of the descriptor pooled into one block.
pub const BLOCK_COLS: usize = 8;

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

/// Heading-invariant similarity of a query (both headings) and a candidate (forward).
#[inline]
pub fn similarity(query: &[Vec<f32>; 2], candidate: &[f32]) -> f32 {
    dot(&query[0], candidate).max(dot(&query[1], candidate))
}

/// Heading-invariant similarity of a query (both headings, f32) and one quantised row:
/// both dot products in one pass over the row, so it is read from memory once.
#[inline]
fn similarity_i8(query: &[Vec<f32>; 2], row: &[i8], scale: f32) -> f32 {
    let (mut a, mut b) = ([0.0f32; 8], [0.0f32; 8]);
    let (qf, qr) = (query[0].chunks_exact(8), query[1].chunks_exact(8));
    let rows = row.chunks_exact(8);
    let (tf, tr, tx) = (qf.remainder(), qr.remainder(), rows.remainder());
    for ((f, r), x) in qf.zip(qr).zip(rows) {
        for k in 0..8 {
            let v = f32::from(x[k]);
            a[k] += f[k] * v;
            b[k] += r[k] * v;
        }
    }
    let (mut sa, mut sb) = (a.iter().sum::<f32>(), b.iter().sum::<f32>());
    for ((f, r), x) in tf.iter().zip(tr).zip(tx) {
        sa += f * f32::from(*x);
        sb += r * f32::from(*x);
    }
    sa.max(sb) * scale
}

/// Signatures of many landmarks in one contiguous array (row `k` = landmark `k`), quantised
/// to `i8` with one scale per row: the scan over a large database is bound by memory
/// traffic (f32 rows: 1.9 ms for 10,000 on a loaded 2-core machine, `retrieval` bench), and
/// a quarter of the bytes moves a quarter as much. The ranking only needs the order of the
/// similarities; a unit vector of 512 values quantised to 127 levels of its largest keeps
/// them to about 1e-3.
#[derive(Clone, Debug, Default)]
pub struct CoarseIndex {
    dim: usize,
    values: Vec<i8>,
    scales: Vec<f32>,
}

impl CoarseIndex {
    /// Appends one signature; all must share a length (the database checks grids first).
    pub fn push(&mut self, signature: &[f32]) {
        if self.scales.is_empty() {
            self.dim = signature.len();
        }
        let largest = signature.iter().fold(0.0f32, |m, v| m.max(v.abs()));
        let scale = if largest > 0.0 { largest / 127.0 } else { 1.0 };
        if signature.len() == self.dim {
            self.values.extend(
                signature
                    .iter()
                    .map(|v| (v / scale).round().clamp(-127.0, 127.0) as i8),
            );
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

    /// Similarity of `query` (both headings) to signature `k` (0 if out of range).
    pub fn similarity(&self, query: &[Vec<f32>; 2], k: usize) -> f32 {
        match (
            self.values.get(k * self.dim..(k + 1) * self.dim),
            self.scales.get(k),
        ) {
            (Some(row), Some(&scale)) => similarity_i8(query, row, scale),
            _ => 0.0,
        }
    }

    /// The `length` candidates among `indices` most similar to `query` (both headings), best
    /// first; ties by index. `parallel`: rayon over chunks of the candidates.
    pub fn short_list(
        &self,
        query: &[Vec<f32>; 2],
        indices: &[usize],
        length: usize,
        parallel: bool,
    ) -> Vec<usize> {
        use rayon::prelude::*;
        let score = |&k: &usize| (self.similarity(query, k), k);
        let mut scored: Vec<(f32, usize)> = if parallel {
            indices.par_iter().with_min_len(1024).map(score).collect()
        } else {
            indices.iter().map(score).collect()
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
        let q = signatures(&field(rows, cols, 7), &observed, rows, cols);
        let all: Vec<usize> = (0..300).filter(|k| k % 3 != 0).collect();
        let mut brute: Vec<(f32, usize)> =
            all.iter().map(|&k| (index.similarity(&q, k), k)).collect();
        brute.sort_by(|a, b| b.0.total_cmp(&a.0).then(a.1.cmp(&b.1)));
        let expected: Vec<usize> = brute.iter().take(10).map(|x| x.1).collect();
        assert_eq!(index.short_list(&q, &all, 10, false), expected);
        assert_eq!(index.short_list(&q, &all, 10, true), expected);
        assert_eq!(index.short_list(&q, &all, 1000, false).len(), all.len());
        assert_eq!(index.short_list(&q, &all, 10, false)[0], 7);
        // Quantisation keeps the similarities to about 1e-3.
        let exact = signature(&field(rows, cols, 11), &observed, rows, cols);
        assert!((index.similarity(&q, 11) - similarity(&q, &exact)).abs() < 5e-3);
        assert!((index.similarity(&q, 7) - 1.0).abs() < 5e-3);
    }
}
