//! Unique mutual nearest neighbours between two keypoint sets (paper §III-B, Algorithm 1
//! line 8): query keypoint `i` and candidate keypoint `j` correspond iff `j` is the nearest
//! candidate of `i` and `i` the nearest query of `j`. Mutual nearest neighbours are one-to-one
//! by construction; "unique" additionally drops ties (two equally near neighbours), which
//! occur on flat or duplicated patches and carry no evidence.

use faer::Mat;

/// Index pairs `(query keypoint, candidate keypoint)` that are unique mutual nearest
/// neighbours in the `N_i x N_j` distance matrix (infinite distances never match).
///
/// Two element-wise passes over the columns (contiguous in faer's column-major storage),
/// branch-free so that the compiler vectorises them: each row's minimum, then how many
/// columns hold it and which. A row with a unique finite minimum `m` at column `j` is a match
/// iff no other entry of column `j` is `<= m`. A single pass updating a (best, index, unique)
/// triple per row and column branched on every entry and cost three times the division pass
/// (perf, `retrieval` bench); it is kept as the reference in the tests.
pub fn mutual_nearest(dist: &Mat<f32>) -> Vec<(usize, usize)> {
    pulp::Arch::new().dispatch(MutualNearest(dist))
}

/// [`mutual_nearest`] compiled for the CPU's best instruction set ([`pulp`] dispatch):
/// comparisons and selects only, so the same result on every instruction set.
struct MutualNearest<'a>(&'a Mat<f32>);

impl pulp::WithSimd for MutualNearest<'_> {
    type Output = Vec<(usize, usize)>;

    #[inline(always)]
    fn with_simd<S: pulp::Simd>(self, _simd: S) -> Self::Output {
        mutual_nearest_body(self.0)
    }
}

#[inline(always)]
fn mutual_nearest_body(dist: &Mat<f32>) -> Vec<(usize, usize)> {
    let (ni, nj) = (dist.nrows(), dist.ncols());
    let mut row_min = vec![f32::INFINITY; ni];
    for j in 0..nj {
        for (r, &d) in row_min.iter_mut().zip(dist.col_as_slice(j)) {
            // False for NaN and for +inf against +inf: neither becomes a minimum.
            *r = if d < *r { d } else { *r };
        }
    }
    let (mut row_count, mut row_arg) = (vec![0u32; ni], vec![0u32; ni]);
    for j in 0..nj {
        let col = dist.col_as_slice(j);
        for (((c, a), &d), &m) in row_count
            .iter_mut()
            .zip(&mut row_arg)
            .zip(col)
            .zip(&row_min)
        {
            *c += u32::from(d == m);
            *a = if d == m { j as u32 } else { *a };
        }
    }
    let mut pairs = Vec::new();
    for (i, ((&m, &count), &j)) in row_min.iter().zip(&row_count).zip(&row_arg).enumerate() {
        if !m.is_finite() || count != 1 {
            continue;
        }
        let col = dist.col_as_slice(j as usize);
        let at_most: u32 = col.iter().map(|&d| u32::from(d <= m)).sum();
        if at_most == 1 {
            pairs.push((i, j as usize));
        }
    }
    pairs
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn mutual_and_unique_only() {
        let d = Mat::<f32>::from_fn(3, 3, |i, j| match (i, j) {
            (0, 0) => 0.1,
            (1, 1) => 0.2,
            (2, 1) => 0.2, // tie with (1, 1): column 1 not unique
            (2, 2) => 0.5,
            _ => 1.0,
        });
        assert_eq!(mutual_nearest(&d), vec![(0, 0)]);
    }

    /// The straightforward single-pass definition: per row and column the strictly smallest
    /// finite distance, unique unless another entry equals it.
    fn reference(dist: &Mat<f32>) -> Vec<(usize, usize)> {
        let (ni, nj) = (dist.nrows(), dist.ncols());
        let mut row_best = vec![(f32::INFINITY, usize::MAX, false); ni];
        let mut col_best = vec![(f32::INFINITY, usize::MAX, false); nj];
        for j in 0..nj {
            for i in 0..ni {
                let d = dist[(i, j)];
                if !d.is_finite() {
                    continue;
                }
                for (best, other) in [(&mut row_best[i], j), (&mut col_best[j], i)] {
                    if d < best.0 {
                        *best = (d, other, true);
                    } else if d == best.0 {
                        best.2 = false;
                    }
                }
            }
        }
        (0..ni)
            .filter_map(|i| {
                let (_, j, unique) = row_best[i];
                (unique && j < nj && col_best[j].2 && col_best[j].1 == i).then_some((i, j))
            })
            .collect()
    }

    #[test]
    fn matches_the_single_pass_reference_with_ties_and_gaps() {
        let mut rng = crate::matching::synthetic::Rng::new(5);
        let mut found = 0;
        for trial in 0..400 {
            let (ni, nj) = (1 + trial % 70, 1 + (trial * 7) % 65);
            // Few distinct levels (many ties), some infinite and NaN entries, a signed zero.
            let levels = 2 + trial % 40;
            let d = Mat::<f32>::from_fn(ni, nj, |_, _| {
                let u = rng.uniform();
                if u < 0.1 {
                    f32::INFINITY
                } else if u < 0.12 {
                    f32::NAN
                } else if u < 0.13 {
                    -0.0
                } else {
                    (rng.uniform() * levels as f64).floor() as f32
                }
            });
            let expected = reference(&d);
            found += expected.len();
            assert_eq!(mutual_nearest(&d), expected, "trial {trial}");
        }
        assert!(found > 100, "{found}");
    }
}
