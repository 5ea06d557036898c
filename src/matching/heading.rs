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
}
