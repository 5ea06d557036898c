//! Geometric verification (paper §III-C): rigid consensus of the correspondences in the
//! `(z, p)` chart.
//!
//! The chart is aligned with the corridor axis and gravity, and the heading is fixed before
//! matching, so a rigid motion of the chart is a translation `(dz, dp)` with `p` circular.
//! Every correspondence votes for one translation; each vote inside the plausible range
//! (`|dz| <= max_shift_z_cells`, `|dp| <= max_shift_p_cells`) is a hypothesis, and the
//! hypothesis with the most correspondences within `(verify_tolerance_z_cells,
//! verify_tolerance_p_cells)` wins (exhaustive, `O(n^2)` for `n <= max_keypoints`, hence exact
//! and deterministic, unlike RANSAC). Its inliers give `K`, and their mean offset (circular
//! mean in `p`) gives `(dz, dp)`.
//!
//! Choices (the paper is silent): tolerance 1 row x 2 columns, since keypoints sit on cell
//! centres and a sub-cell misalignment moves an extremum by one cell; plausible shifts 3 rows
//! (the same boundary detected by the DoG lands within a few cells, DESIGN: ~10 cm feature
//! competition) and 16 columns (22.5°, far above the gravity error of an IMU). A random
//! correspondence then falls inside the winning box with probability
//! `3 * 5 / (16 * 256) ~ 0.4 %`, so wrong pairs reach K <= 3 on the synthetic set while true
//! pairs reach K = 8–31 (mean 20; 50 joints x 2 random views, tunnel grid).

use crate::config::MatchingConfig;

/// One correspondence in grid cells: query `(row, col)` and candidate `(row, col)`, both in
/// the same heading.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Correspondence {
    /// Query keypoint cell.
    pub query: (usize, usize),
    /// Candidate keypoint cell.
    pub candidate: (usize, usize),
}

/// The consensus of a set of correspondences.
#[derive(Clone, Copy, Debug, PartialEq, Default)]
pub struct Consensus {
    /// Number of inliers `K`.
    pub inliers: usize,
    /// Mean axial offset candidate - query, in rows.
    pub dz_cells: f64,
    /// Mean circumferential offset candidate - query, in columns, in `[-cols/2, cols/2)`.
    pub dp_cells: f64,
}

fn wrap(d: isize, cols: usize) -> isize {
    let c = cols as isize;
    (d + c / 2).rem_euclid(c) - c / 2
}

fn offset(c: &Correspondence, cols: usize) -> (isize, isize) {
    (
        c.candidate.0 as isize - c.query.0 as isize,
        wrap(c.candidate.1 as isize - c.query.1 as isize, cols),
    )
}

/// Rigid (translation) consensus in the `(z, p)` chart; see the module docs.
pub fn consensus(matches: &[Correspondence], cols: usize, cfg: &MatchingConfig) -> Consensus {
    let offsets: Vec<(isize, isize)> = matches.iter().map(|c| offset(c, cols)).collect();
    let (tz, tp) = (
        cfg.verify_tolerance_z_cells as isize,
        cfg.verify_tolerance_p_cells as isize,
    );
    let (mz, mp) = (
        cfg.max_shift_z_cells as isize,
        cfg.max_shift_p_cells as isize,
    );
    let inliers_of = |h: (isize, isize)| {
        offsets
            .iter()
            .filter(|o| (o.0 - h.0).abs() <= tz && wrap(o.1 - h.1, cols).abs() <= tp)
            .count()
    };
    let mut best: Option<((isize, isize), usize)> = None;
    for &h in &offsets {
        if h.0.abs() > mz || h.1.abs() > mp {
            continue;
        }
        let k = inliers_of(h);
        let better = match best {
            None => true,
            Some((bh, bk)) => {
                k > bk || (k == bk && (h.0.abs() + h.1.abs(), h) < (bh.0.abs() + bh.1.abs(), bh))
            }
        };
        if better {
            best = Some((h, k));
        }
    }
    let Some((h, k)) = best else {
        return Consensus::default();
    };
    let (mut sz, mut sp) = (0.0, 0.0);
    for o in &offsets {
        let dp = wrap(o.1 - h.1, cols);
        if (o.0 - h.0).abs() <= tz && dp.abs() <= tp {
            sz += o.0 as f64;
            sp += (h.1 + dp) as f64;
        }
    }
    let half = cols as f64 / 2.0;
    let dp_cells = (sp / k as f64 + half).rem_euclid(cols as f64) - half;
    Consensus {
        inliers: k,
        dz_cells: sz / k as f64,
        dp_cells,
    }
}

/// Without verification (ablation): every correspondence counts, offsets are plain means.
pub fn no_consensus(matches: &[Correspondence], cols: usize) -> Consensus {
    if matches.is_empty() {
        return Consensus::default();
    }
    let n = matches.len() as f64;
    let (sz, sp) = matches.iter().fold((0.0, 0.0), |(z, p), c| {
        let o = offset(c, cols);
        (z + o.0 as f64, p + o.1 as f64)
    });
    Consensus {
        inliers: matches.len(),
        dz_cells: sz / n,
        dp_cells: sp / n,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::config::DecodConfig;

    #[test]
    fn finds_the_shift_across_the_seam() {
        let cfg = DecodConfig::tunnel().matching;
        // True shift: +1 row, -3 columns; keypoints near p = 0 wrap around the seam.
        let mut m: Vec<Correspondence> = (0..12)
            .map(|k| {
                let q = (2 + k % 10, (250 + 7 * k) % 256);
                Correspondence {
                    query: q,
                    candidate: (q.0 + 1, (q.1 + 253) % 256),
                }
            })
            .collect();
        m.push(Correspondence {
            query: (3, 40),
            candidate: (9, 170),
        });
        let c = consensus(&m, 256, &cfg);
        assert_eq!(c.inliers, 12);
        assert!((c.dz_cells - 1.0).abs() < 1e-12);
        assert!((c.dp_cells + 3.0).abs() < 1e-12);
    }
}
