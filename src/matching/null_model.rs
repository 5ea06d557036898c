//! Acceptance calibrated by a null model (not in the paper, which fixes `K >= 9` or `K >= 15`).
//!
//! A fixed inlier threshold means different things for different keypoint counts, overlaps,
//! shift windows and database sizes: 16 keypoints rarely give 9 chance inliers, 64 keypoints
//! with structured positions (a seam row, longitudinal seams at fixed angles) easily do, and
//! a query compared with 2,000 candidates meets far more chance agreement than one compared
//! with 20. So the threshold follows from the chance that *this* pair reaches `K` by accident.
//!
//! **Null hypothesis.** The pair shows different surfaces: its `M` mutual matches pair
//! keypoints as if at random, so each correspondence's offset `(dz, dp)` (candidate minus
//! query, in the chosen heading) is drawn from the offsets of *all* `N_i x N_j` keypoint
//! pairs, `P(o) = #{(i, j): c_j - q_i = o} / (N_i N_j)`. Built from the keypoints' actual
//! positions, this null already holds the structure that makes chance agreement likely
//! (keypoints crowded on the boundary row in both descriptors, or on seams at the same
//! angles): a uniform null would promise far fewer chance inliers than real wrong pairs show.
//!
//! **Pair p-value.** Verification picks the translation `h` within the shift window
//! (`|dz| <= max_shift_z_cells`, `|dp| <= max_shift_p_cells`) whose tolerance box holds the
//! most offsets. Under the null the count in box `h` is `Binomial(M, q_h)` with
//! `q_h = sum of P(o)` over the box; the chance that the best box reaches `K` is bounded by
//! the union bound `sum_h P(Bin(M, q_h) >= K)`. Overlapping boxes make it conservative, but
//! the scan-statistic shortcut of dividing by the box area (each cluster counted once per
//! box covering it) promised 5 % and delivered 10 % on 400 unrelated candidates
//! (`matching::tests::null_model_rejects_unrelated_pairs_at_the_promised_rate`): clusters of
//! four chance offsets are usually spread, covered by few box positions, not by all 15.
//!
//! **Query level.** A query compares its boundary with `n` distinct database boundaries
//! under two headings, so the family-wise chance of a false Top-1 is at most
//! `1 - (1 - p)^(2n)` (within a run the odometry's direction of travel usually leaves one
//! heading per candidate, `heading::prior`; the family still counts two, which only makes
//! the test stricter). The best candidate is accepted iff this is at most
//! `false_alarm_rate`. It is ambiguous (`not_unique`) when the runner-up — another physical
//! boundary: views of one boundary are one candidate — is itself beyond chance at
//! `uniqueness_alpha` *and* the best does not lead it significantly: under "both are equally
//! similar" each of the `K1 + K2` inliers is as likely to fall to either, and a lead as large
//! as the observed one has chance `P(Bin(K1 + K2, 1/2) >= K1)` ([`as_likely`]). Structured
//! corridors need the second clause: in the simulated shield tunnel the segment layout repeats
//! every two rings, so the ring 3 m away matches far beyond chance (K = 13) while the right
//! one leads with K = 38 (chance of such a lead 2e-4); identical joints give leads like
//! 14 to 12, which are not significant.
//!
//! Chance agreement is not the only way to be wrong: views of identical joints taken from the
//! same distance share sensor-relative artefacts. On the simulated aliased hume pipe
//! (identical joints, seed 2, auto configuration) two wrong loops (K 14 and 8 against
//! runner-ups of 4, 12 m off) passed both tests. The paper-mode count margin
//! (`uniqueness_sigma`) would reject them, but it is not invariant to the keypoint count: with
//! 16 keypoints it cut recall on the synthetic pipe from 0.66 to 0.06. They are left to the
//! loop selection (`decod_rs.selection`): a 12 m correction after 40 m of travel is not
//! consistent with the odometry.

use super::keypoints::AtCell;
#[cfg(test)]
use super::keypoints::Keypoint;
use super::{Heading, heading::flip_cell};
use crate::config::MatchingConfig;

/// `ln(n!)` for small `n` (exact sum; `n` is at most a few hundred keypoints).
fn ln_factorial(n: usize) -> f64 {
    (2..=n).map(|k| (k as f64).ln()).sum()
}

/// `P(Binomial(m, q) >= k)`, summed in log space (stable for tiny `q`).
pub fn binomial_tail(m: usize, q: f64, k: usize) -> f64 {
    BinomialTail::new(m, k).at(q)
}

/// `P(Binomial(m, q) >= k)` for fixed `m` and `k` and any `q`: the log binomial coefficients
/// `ln C(m, j)`, `j = k..=m`, are summed once. [`pair_p_value`] evaluates the tail at 231
/// box probabilities per pair; recomputing the coefficients' `3m` logarithms for each took
/// a quarter of a coarse query's time (perf, `retrieval` bench).
#[derive(Clone, Debug)]
pub struct BinomialTail {
    m: usize,
    k: usize,
    /// `ln C(m, j)` for `j = k..=m` (empty when `k == 0` or `k > m`).
    ln_choose: Vec<f64>,
}

impl BinomialTail {
    /// The tail `P(Bin(m, .) >= k)`.
    pub fn new(m: usize, k: usize) -> Self {
        let mut ln_choose = Vec::new();
        if k > 0 && k <= m {
            let lm = ln_factorial(m);
            let mut ln_fact_j = ln_factorial(k);
            let mut ln_fact_mj = ln_factorial(m - k);
            for j in k..=m {
                if j > k {
                    ln_fact_j += (j as f64).ln();
                    ln_fact_mj -= ((m - j + 1) as f64).ln();
                }
                ln_choose.push(lm - ln_fact_j - ln_fact_mj);
            }
        }
        Self { m, k, ln_choose }
    }

    /// The tail at success probability `q`.
    pub fn at(&self, q: f64) -> f64 {
        let (m, k) = (self.m, self.k);
        if k == 0 {
            return 1.0;
        }
        if k > m || q <= 0.0 {
            return 0.0;
        }
        if q >= 1.0 {
            return 1.0;
        }
        let (lq, l1q) = (q.ln(), (-q).ln_1p());
        let mut total = 0.0;
        for (c, j) in self.ln_choose.iter().zip(k..=m) {
            total += (c + j as f64 * lq + (m - j) as f64 * l1q).exp();
        }
        total.min(1.0)
    }
}

/// Offsets candidate minus query, in cells, `dp` wrapped to `[-cols/2, cols/2)`.
fn wrapped(d: isize, cols: usize) -> isize {
    let c = cols as isize;
    (d + c / 2).rem_euclid(c) - c / 2
}

/// The chance that a pair of different surfaces with these keypoints and `matches` mutual
/// matches verifies with `inliers` or more (module docs). 1 when nothing was verified.
pub fn pair_p_value<K: AtCell>(
    query: &[K],
    candidate: &[K],
    heading: Heading,
    grid: (usize, usize),
    matches: usize,
    inliers: usize,
    cfg: &MatchingConfig,
) -> f64 {
    let (rows, cols) = grid;
    if inliers == 0 || matches == 0 || query.is_empty() || candidate.is_empty() {
        return 1.0;
    }
    let (tz, tp) = (
        cfg.verify_tolerance_z_cells as isize,
        cfg.verify_tolerance_p_cells as isize,
    );
    let (mz, mp) = (
        cfg.max_shift_z_cells as isize,
        cfg.max_shift_p_cells as isize,
    );
    // Histogram of every keypoint pair's offset inside the window widened by the tolerance.
    let (ez, ep) = (mz + tz, (mp + tp).min(cols as isize / 2));
    let (w, h) = ((2 * ep + 1) as usize, (2 * ez + 1) as usize);
    let mut hist = vec![0.0f64; w * h];
    for kq in query {
        let (r, c) = kq.cell();
        let (qr, qc) = match heading {
            Heading::Forward => (r, c),
            Heading::Reversed => flip_cell(r, c, rows, cols),
        };
        for kc in candidate {
            let (cr, cc) = kc.cell();
            let dz = cr as isize - qr as isize;
            let dp = wrapped(cc as isize - qc as isize, cols);
            if dz.abs() <= ez && dp.abs() <= ep {
                hist[((dz + ez) as usize) * w + (dp + ep) as usize] += 1.0;
            }
        }
    }
    let norm = 1.0 / (query.len() * candidate.len()) as f64;
    let tail_of = BinomialTail::new(matches, inliers);
    // Box counts are small integers shared by many boxes: each tail is computed once.
    let mut memo: Vec<(f64, f64)> = Vec::new();
    let mut sum = 0.0;
    let mut largest: f64 = 0.0;
    for hz in -mz..=mz {
        for hp in -mp.min(ep - tp)..=mp.min(ep - tp) {
            let mut q = 0.0;
            for dz in (hz - tz)..=(hz + tz) {
                for dp in (hp - tp)..=(hp + tp) {
                    q += hist[((dz + ez) as usize) * w + (dp + ep) as usize];
                }
            }
            let tail = match memo.iter().find(|(count, _)| *count == q) {
                Some(&(_, t)) => t,
                None => {
                    let t = tail_of.at(q * norm);
                    memo.push((q, t));
                    t
                }
            };
            sum += tail;
            largest = largest.max(tail);
        }
    }
    sum.max(largest).min(1.0)
}

/// The chance that the best candidate leads the runner-up by this much although both are
/// equally similar to the query: `P(Bin(K1 + K2, 1/2) >= K1)` (each inlier as likely to fall
/// to either).
pub fn as_likely(k_best: usize, k_runner_up: usize) -> f64 {
    binomial_tail(k_best + k_runner_up, 0.5, k_best)
}

/// Family-wise chance of a false Top-1 over `candidates` boundaries and both headings.
pub fn family_wise(p_pair: f64, candidates: usize) -> f64 {
    let tests = 2.0 * candidates.max(1) as f64;
    // 1 - (1 - p)^n, stable for tiny p.
    -(tests * (-p_pair.clamp(0.0, 1.0)).ln_1p()).exp_m1()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::config::DecodConfig;
    use crate::matching::keypoints::KeptCell;

    fn kp(row: usize, col: usize) -> Keypoint {
        Keypoint {
            row,
            col,
            response: 1.0,
        }
    }

    #[test]
    fn binomial_tail_matches_direct_sums() {
        // P(Bin(4, 0.5) >= 3) = (4 + 1) / 16.
        assert!((binomial_tail(4, 0.5, 3) - 5.0 / 16.0).abs() < 1e-12);
        assert!((binomial_tail(10, 0.1, 0) - 1.0).abs() < 1e-15);
        assert_eq!(binomial_tail(3, 0.2, 4), 0.0);
        // P(Bin(40, 0.004) >= 5) ~ C(40,5) q^5 = 658008 * 1.024e-12.
        let p = binomial_tail(40, 0.004, 5);
        assert!(
            (p / (658_008.0 * 0.004f64.powi(5)) - 1.0).abs() < 0.2,
            "{p}"
        );
    }

    /// The tail as first written: coefficients recomputed on every call.
    fn binomial_tail_reference(m: usize, q: f64, k: usize) -> f64 {
        if k == 0 {
            return 1.0;
        }
        if k > m || q <= 0.0 {
            return 0.0;
        }
        if q >= 1.0 {
            return 1.0;
        }
        let (lq, l1q) = (q.ln(), (-q).ln_1p());
        let lm = ln_factorial(m);
        let mut total = 0.0;
        let mut ln_fact_j = ln_factorial(k);
        let mut ln_fact_mj = ln_factorial(m - k);
        for j in k..=m {
            if j > k {
                ln_fact_j += (j as f64).ln();
                ln_fact_mj -= ((m - j + 1) as f64).ln();
            }
            total += (lm - ln_fact_j - ln_fact_mj + j as f64 * lq + (m - j) as f64 * l1q).exp();
        }
        total.min(1.0)
    }

    #[test]
    fn cached_coefficients_give_the_same_bits() {
        for m in [0usize, 1, 5, 30, 64] {
            for k in 0..=m + 1 {
                let tail = BinomialTail::new(m, k);
                for q in [0.0, 1e-9, 0.004, 0.1, 0.5, 0.999, 1.0] {
                    let (a, b) = (tail.at(q), binomial_tail_reference(m, q, k));
                    assert_eq!(a.to_bits(), b.to_bits(), "m {m} k {k} q {q}");
                }
            }
        }
        // And the pair p-value over many random keypoint sets (memoised box counts).
        let cfg = DecodConfig::tunnel().matching;
        let mut rng = crate::matching::synthetic::Rng::new(9);
        let kps = |n: usize, rng: &mut crate::matching::synthetic::Rng| -> Vec<Keypoint> {
            (0..n)
                .map(|_| {
                    kp(
                        (rng.uniform() * 16.0) as usize,
                        (rng.uniform() * 256.0) as usize,
                    )
                })
                .collect()
        };
        for trial in 0..40 {
            let (q, c) = (kps(10 + trial, &mut rng), kps(64 - trial, &mut rng));
            let heading = Heading::BOTH[trial % 2];
            let (m, k) = (5 + trial % 30, 3 + trial % 5);
            let fast = pair_p_value(&q, &c, heading, (16, 256), m, k, &cfg);
            let slow = pair_p_value_reference(&q, &c, heading, (16, 256), m, k, &cfg);
            assert_eq!(fast.to_bits(), slow.to_bits(), "trial {trial}");
        }
    }

    /// [`pair_p_value`] as first written: one tail per box, nothing shared.
    fn pair_p_value_reference(
        query: &[Keypoint],
        candidate: &[Keypoint],
        heading: Heading,
        grid: (usize, usize),
        matches: usize,
        inliers: usize,
        cfg: &MatchingConfig,
    ) -> f64 {
        let (rows, cols) = grid;
        let (tz, tp) = (
            cfg.verify_tolerance_z_cells as isize,
            cfg.verify_tolerance_p_cells as isize,
        );
        let (mz, mp) = (
            cfg.max_shift_z_cells as isize,
            cfg.max_shift_p_cells as isize,
        );
        let ep = (mp + tp).min(cols as isize / 2);
        let mut sum = 0.0;
        let mut largest: f64 = 0.0;
        for hz in -mz..=mz {
            for hp in -mp.min(ep - tp)..=mp.min(ep - tp) {
                let mut q = 0.0;
                for dz in (hz - tz)..=(hz + tz) {
                    for dp in (hp - tp)..=(hp + tp) {
                        for kq in query {
                            let (qr, qc) = match heading {
                                Heading::Forward => (kq.row, kq.col),
                                Heading::Reversed => flip_cell(kq.row, kq.col, rows, cols),
                            };
                            q += candidate
                                .iter()
                                .filter(|kc| {
                                    kc.row as isize - qr as isize == dz
                                        && wrapped(kc.col as isize - qc as isize, cols) == dp
                                })
                                .count() as f64;
                        }
                    }
                }
                let p = q * (1.0 / (query.len() * candidate.len()) as f64);
                let tail = binomial_tail_reference(matches, p, inliers);
                sum += tail;
                largest = largest.max(tail);
            }
        }
        sum.max(largest).min(1.0)
    }

    #[test]
    fn crowded_keypoints_make_chance_agreement_likelier() {
        let cfg = DecodConfig::tunnel().matching;
        // Spread keypoints: random-looking positions over the grid.
        let spread: Vec<Keypoint> = (0..40).map(|k| kp((k * 7) % 16, (k * 97) % 256)).collect();
        // Crowded: every keypoint on the boundary row (8), at six seam angles.
        let crowded: Vec<Keypoint> = (0..40).map(|k| kp(8, (k % 6) * 43)).collect();
        let grid = (16, 256);
        let p_spread = pair_p_value(&spread, &spread, Heading::Forward, grid, 30, 8, &cfg);
        let p_crowded = pair_p_value(&crowded, &crowded, Heading::Forward, grid, 30, 8, &cfg);
        assert!(p_spread < 1e-4, "{p_spread}");
        assert!(p_crowded > 1e-2, "{p_crowded}");
        // More inliers are always less likely by chance.
        let p9 = pair_p_value(&spread, &spread, Heading::Forward, grid, 30, 9, &cfg);
        assert!(p9 < p_spread);
        // A view keeps its keypoints' cells only: the same chance, under both headings.
        let kept: Vec<KeptCell> = spread.iter().map(KeptCell::from).collect();
        for heading in Heading::BOTH {
            assert_eq!(
                pair_p_value(&kept, &kept, heading, grid, 30, 8, &cfg).to_bits(),
                pair_p_value(&spread, &spread, heading, grid, 30, 8, &cfg).to_bits()
            );
        }
    }

    #[test]
    fn a_lead_is_significant_only_when_large() {
        assert!(as_likely(38, 13) < 1e-3);
        assert!(as_likely(14, 12) > 0.3);
        assert!((as_likely(1, 1) - 0.75).abs() < 1e-12);
    }

    #[test]
    fn family_wise_grows_with_the_candidates_compared() {
        let p = 1e-5;
        assert!((family_wise(p, 20) - 40.0 * p).abs() < 1e-7);
        assert!(family_wise(p, 2000) > 30.0 * family_wise(p, 20));
        assert!(family_wise(1.0, 1) <= 1.0);
    }
}
