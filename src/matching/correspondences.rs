//! Unique mutual nearest neighbours between two keypoint sets (paper §III-B, Algorithm 1
//! line 8): query keypoint `i` and candidate keypoint `j` correspond iff `j` is the nearest
//! candidate of `i` and `i` the nearest query of `j`. Mutual nearest neighbours are one-to-one
//! by construction; "unique" additionally drops ties (two equally near neighbours), which
//! occur on flat or duplicated patches and carry no evidence.

use faer::Mat;

/// Index pairs `(query keypoint, candidate keypoint)` that are unique mutual nearest
/// neighbours in the `N_i x N_j` distance matrix (infinite distances never match).
pub fn mutual_nearest(dist: &Mat<f32>) -> Vec<(usize, usize)> {
    let (ni, nj) = (dist.nrows(), dist.ncols());
    // Best and whether it is unique, per row and per column.
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
    let mut pairs = Vec::new();
    for (i, &(_, j, unique)) in row_best.iter().enumerate() {
        if unique && j < nj {
            let (_, back, col_unique) = col_best[j];
            if col_unique && back == i {
                pairs.push((i, j));
            }
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
}
