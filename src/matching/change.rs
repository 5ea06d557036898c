//! Change between two sessions' views of one boundary (issue 12, not in the paper): the
//! normalised descriptor difference after alignment.
//!
//! Both descriptors are normalised as the matcher sees them (Eq. 2 residual and the `p`
//! smoothing of `MatchingConfig::field_smoothing_sigma_m`), the candidate is brought to the
//! query's heading (§III-B: the 180° grid rotation) and shifted by the verified offsets
//! `(dz, dp)` of the accepted pair, and over the mutually observed cells
//!
//! `change = sum (q - c)^2 / (sum q^2 + sum c^2)`,
//!
//! 0 for identical fields, 1 for uncorrelated ones of any amplitude, 2 for opposite ones.
//! Two views of an unchanged joint differ by sensor noise and sub-cell misalignment only; a
//! displaced segment, a joint opened on one side or a deposit adds structure that one view
//! has and the other lacks. What Eq. 2 removes (a uniform widening of a joint, a radius
//! change) is invisible here by design: the same nuisance model that makes two views
//! comparable cannot tell that change from a contour error.

use super::heading::flip_grid;
use super::normalise::{self, Normalisation};
use super::{Heading, check_grids};
use crate::config::MatchingConfig;
use crate::error::Result;
use crate::landmark::Landmark;

/// The aligned comparison of a query and a candidate.
#[derive(Clone, Debug, PartialEq)]
pub struct Change {
    /// Normalised difference over the mutually observed cells (module docs); NaN if none.
    pub normalised_difference: f64,
    /// Number of mutually observed cells.
    pub cells: usize,
    /// `q - c` per query cell, row-major `rows x cols`; NaN where not mutually observed.
    pub difference: Vec<f64>,
}

/// Cells whose raw offset exceeds this fraction of the section's radius (and the cells
/// around them) are left out: an opening such as a pipe connection looks different from
/// every distance, which is not a change of the wall (on the simulated hume pipe a 25 cm
/// deep lateral connection ranked first without this).
pub const WALL_FRACTION: f64 = 0.1;

/// The matcher's field of one landmark and its observed mask, without the cells off the
/// wall ([`WALL_FRACTION`]) and their neighbours.
fn field(l: &Landmark, cfg: &MatchingConfig) -> (Vec<f64>, Vec<bool>) {
    let d = &l.descriptor;
    let raw = normalise::normalised_field(d, Normalisation::from_config(cfg), false);
    let sigma = if d.perimeter_m > 0.0 {
        cfg.field_smoothing_sigma_m * d.cols as f64 / d.perimeter_m
    } else {
        0.0
    };
    let (f, mut observed) = normalise::smooth_along_p(&raw, &d.observed, d.rows, d.cols, sigma);
    let limit = WALL_FRACTION * l.radius_m;
    let far: Vec<bool> = d
        .offsets_m
        .iter()
        .map(|v| f64::from(v.abs()) > limit)
        .collect();
    for r in 0..d.rows {
        for c in 0..d.cols {
            let near_far = (r.saturating_sub(1)..(r + 2).min(d.rows)).any(|rr| {
                [c + d.cols - 1, c, c + 1]
                    .iter()
                    .any(|&cc| far[rr * d.cols + cc % d.cols])
            });
            if near_far {
                observed[r * d.cols + c] = false;
            }
        }
    }
    (f, observed)
}

/// The change between `query` and `candidate` aligned by `heading` and the pair's offsets
/// `dz_m` (metres) and `dp` (fraction of the circumference), as in [`super::PairResult`].
pub fn aligned_change(
    query: &Landmark,
    candidate: &Landmark,
    heading: Heading,
    dz_m: f64,
    dp: f64,
    cfg: &MatchingConfig,
) -> Result<Change> {
    check_grids(query, candidate)?;
    query.validate()?;
    candidate.validate()?;
    let (rows, cols) = (query.descriptor.rows, query.descriptor.cols);
    let (q, q_obs) = field(query, cfg);
    let (mut c, mut c_obs) = field(candidate, cfg);
    if heading == Heading::Reversed {
        c = flip_grid(&c);
        c_obs = flip_grid(&c_obs);
    }
    let finite = |x: f64| if x.is_finite() { x } else { 0.0 };
    let dz = (finite(dz_m) / query.descriptor.cell_z_m).round() as isize;
    let dpc = (finite(dp) * cols as f64).round() as isize;
    let mut difference = vec![f64::NAN; rows * cols];
    let (mut num, mut den, mut cells) = (0.0, 0.0, 0usize);
    for r in 0..rows {
        let rc = r as isize + dz;
        if rc < 0 || rc >= rows as isize {
            continue;
        }
        for col in 0..cols {
            let cc = (col as isize + dpc).rem_euclid(cols as isize) as usize;
            let (i, j) = (r * cols + col, rc as usize * cols + cc);
            if q_obs[i] && c_obs[j] {
                let d = q[i] - c[j];
                difference[i] = d;
                num += d * d;
                den += q[i] * q[i] + c[j] * c[j];
                cells += 1;
            }
        }
    }
    let normalised_difference = if den > 0.0 { num / den } else { f64::NAN };
    Ok(Change {
        normalised_difference,
        cells,
        difference,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::config::DecodConfig;
    use crate::matching::compare;
    use crate::matching::synthetic::{Grid, JointSurface, Observation, Rng, SurfaceParams};

    #[test]
    fn an_unchanged_joint_differs_less_than_another_joint() {
        let cfg = DecodConfig::pipe().matching;
        let g = Grid::pipe();
        let mut rng = Rng::new(4);
        let joint = |id| JointSurface::new(g, SurfaceParams::for_grid(&g), 2, id);
        let a = joint(1).observe(&Observation::random(&g, 0.0, false, &mut rng), 1);
        let b = joint(1).observe(&Observation::random(&g, 100.0, true, &mut rng), 2);
        let other = joint(2).observe(&Observation::random(&g, 200.0, true, &mut rng), 3);
        let pair = compare(&a, &b, &cfg).unwrap();
        assert_eq!(pair.heading, Heading::Reversed);
        let same = aligned_change(&a, &b, pair.heading, pair.dz_m, pair.dp, &cfg).unwrap();
        let wrong = aligned_change(&a, &other, pair.heading, pair.dz_m, pair.dp, &cfg).unwrap();
        assert!(same.cells > 1000, "{}", same.cells);
        assert!(
            same.normalised_difference < 0.6 * wrong.normalised_difference,
            "{} vs {}",
            same.normalised_difference,
            wrong.normalised_difference
        );
        // Unaligned (wrong heading), the same joint looks changed.
        let unaligned = aligned_change(&a, &b, Heading::Forward, 0.0, 0.0, &cfg).unwrap();
        assert!(unaligned.normalised_difference > same.normalised_difference);
        let self_change = aligned_change(&a, &a, Heading::Forward, 0.0, 0.0, &cfg).unwrap();
        assert_eq!(self_change.normalised_difference, 0.0);
    }
}
