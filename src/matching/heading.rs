//! Relative heading (paper §III-B): a revisit in the opposite direction negates the axial
//! coordinate `z` and reverses the circumferential order while `p = 0` stays at gravity.
//!
//! On the row-major `rows x cols` grid, `z -> -z` maps row `r` to `rows - 1 - r` and
//! `p -> 1 - p` maps column `c` to `cols - 1 - c`: together a 180° rotation of the grid, which
//! is exactly the reversal of the flat row-major array. The same holds for an odd-sized patch
//! centred on a keypoint, so flipping a patch is reversing its flat vector.

use serde::{Deserialize, Serialize};

/// Relative heading between two traversals of the same corridor.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub enum Heading {
    /// Same direction of travel.
    Forward,
    /// Opposite direction (h = 180°): `z -> -z`, `p -> 1 - p`.
    Reversed,
}

impl Heading {
    /// Both headings, in the order they are evaluated (ties go to `Forward`).
    pub const BOTH: [Heading; 2] = [Heading::Forward, Heading::Reversed];

    /// The heading in degrees (0 or 180), as reported to users.
    pub fn degrees(self) -> f64 {
        match self {
            Heading::Forward => 0.0,
            Heading::Reversed => 180.0,
        }
    }
}

/// Cosine of the angle between two landmarks' axes (in one odometry frame) at or beyond
/// which [`prior`] names one heading: 0.5, axes within 60° of parallel or of antiparallel.
/// The axis is oriented with the sensor's forward (`axis.rs`), so it reverses exactly when
/// the direction of travel does; a wrong choice needs the odometry's relative yaw between
/// the two submaps to be off by more than 30° beyond that margin (60° in all), far beyond
/// the few degrees a LiDAR or wheel odometry drifts over a corridor run. Between the two
/// cones (a submap taken while turning round, the sensor across the corridor, where the
/// axis's orientation is arbitrary) both headings are compared.
pub const PRIOR_MIN_COS: f64 = 0.5;

/// The headings worth comparing for two landmarks whose corridor axes are `query` and
/// `candidate` in one odometry frame (beyond the paper, which always compares both): the one
/// the odometry's direction of travel allows when the axes are clearly parallel or
/// antiparallel ([`PRIOR_MIN_COS`]), else both. The other heading would pair each keypoint
/// with its mirror image across the boundary; no physical revisit produces it, and it
/// doubled the exact matcher's work (two patch-distance GEMMs per pair). Non-finite or zero
/// axes (a landmark placed nowhere) give both.
pub fn prior(query: &[f64; 3], candidate: &[f64; 3]) -> &'static [Heading] {
    let dot: f64 = query.iter().zip(candidate).map(|(a, b)| a * b).sum();
    let norms = (query.iter().map(|a| a * a).sum::<f64>()
        * candidate.iter().map(|b| b * b).sum::<f64>())
    .sqrt();
    if !(dot.is_finite() && norms.is_finite() && norms > 0.0) {
        return &Heading::BOTH;
    }
    let cos = dot / norms;
    if cos >= PRIOR_MIN_COS {
        &Heading::BOTH[..1]
    } else if cos <= -PRIOR_MIN_COS {
        &Heading::BOTH[1..]
    } else {
        &Heading::BOTH
    }
}

/// A row-major grid rotated by 180° (`h = 180`): the reversed flat array.
pub fn flip_grid<T: Copy>(grid: &[T]) -> Vec<T> {
    grid.iter().rev().copied().collect()
}

/// Cell `(row, col)` of a `rows x cols` grid after the 180° flip.
#[inline]
pub fn flip_cell(row: usize, col: usize, rows: usize, cols: usize) -> (usize, usize) {
    (rows - 1 - row, cols - 1 - col)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn flat_reversal_is_the_heading_flip() {
        let (rows, cols) = (3, 5);
        let grid: Vec<usize> = (0..rows * cols).collect();
        let flipped = flip_grid(&grid);
        for r in 0..rows {
            for c in 0..cols {
                let (fr, fc) = flip_cell(r, c, rows, cols);
                assert_eq!(flipped[fr * cols + fc], grid[r * cols + c]);
            }
        }
        assert_eq!(flip_grid(&flipped), grid);
    }

    #[test]
    fn prior_names_one_heading_only_when_the_axes_are_clearly_aligned() {
        let x = [1.0, 0.0, 0.0];
        // 50° of relative yaw: still the same direction of travel.
        let (s, c) = 50f64.to_radians().sin_cos();
        assert_eq!(prior(&x, &[c, s, 0.0]), &[Heading::Forward]);
        assert_eq!(prior(&x, &[-c, s, 0.0]), &[Heading::Reversed]);
        // Across the corridor (70° off either way): both.
        let (s, c) = 70f64.to_radians().sin_cos();
        assert_eq!(prior(&x, &[c, s, 0.0]), &Heading::BOTH);
        assert_eq!(prior(&x, &[-c, -s, 0.0]), &Heading::BOTH);
        // Unplaced or degenerate axes: both.
        assert_eq!(prior(&x, &[f64::NAN; 3]), &Heading::BOTH);
        assert_eq!(prior(&[0.0; 3], &x), &Heading::BOTH);
        // Scale does not matter.
        assert_eq!(
            prior(&[3.0, 0.0, 0.0], &[-0.2, 0.0, 0.0]),
            &[Heading::Reversed]
        );
    }
}
