//! The DeCOD descriptor (paper §III-A): the neighbourhood of a boundary unrolled on a
//! `(z, p)` grid, each observed cell the mean signed normal offset `s = n(p)^T (x - c(p))` of
//! its points; 16 x 256 cells over +-2.4 m and the full circumference in the paper
//! (§IV-A.2), with the bottom +-30 deg sector masked against ground returns.
//!
//! Conventions: row `r` covers `z` in `[-H + r dz, -H + (r + 1) dz)` from the landmark origin
//! along the axis (`H = half_length_m`, `dz = 2H / rows`); column `c` covers
//! `p in [c / cols, (c + 1) / cols)` from `e1` (gravity: the bottom of the section) towards
//! `e2 = a x e1`. A heading reversal flips `a` and hence `e2`: `z -> -z`, `p -> 1 - p`, i.e.
//! rows and columns both reversed, `p = 0` still at gravity (paper §III-B).

use crate::boundary::ChartPoint;
use crate::config::DescriptorConfig;
use crate::contour::{ContourSample, ReferenceContour};
use crate::landmark::Descriptor;

/// Contour samples at the column centres `p_c = (c + 0.5) / cols`.
pub fn column_samples(contour: &ReferenceContour, cols: usize) -> Vec<ContourSample> {
    (0..cols)
        .map(|c| contour.sample((c as f64 + 0.5) / cols as f64))
        .collect()
}

/// Whether each column lies in the bottom sector `|theta| <= bottom_mask_deg` about `e1`
/// (theta = polar angle of the column centre about the contour centre).
pub fn bottom_mask(columns: &[ContourSample], bottom_mask_deg: f64) -> Vec<bool> {
    let limit = bottom_mask_deg.to_radians();
    columns
        .iter()
        .map(|s| {
            let wrapped = (s.theta + std::f64::consts::PI).rem_euclid(std::f64::consts::TAU)
                - std::f64::consts::PI;
            wrapped.abs() <= limit
        })
        .collect()
}

/// Builds the descriptor around the boundary at axial position `z_origin` (same axial origin
/// as the chart points). `columns` and `masked` come from [`column_samples`] and
/// [`bottom_mask`] (computed once per submap). One pass over the points, no allocation
/// besides the grid.
pub fn build_descriptor(
    points: &[ChartPoint],
    z_origin: f64,
    contour: &ReferenceContour,
    columns: &[ContourSample],
    masked: &[bool],
    cfg: &DescriptorConfig,
) -> Descriptor {
    let (rows, cols) = (cfg.rows, cfg.cols);
    let half = cfg.half_length_m;
    let cell_z = 2.0 * half / rows as f64;
    let mut sum = vec![0.0; rows * cols];
    // Summed point weights per cell (1 per point with box binning).
    let mut weight = vec![0.0f64; rows * cols];
    for q in points {
        let dz = q.z - z_origin + half;
        if !(0.0..2.0 * half).contains(&dz) {
            continue;
        }
        let c = ((q.p * cols as f64) as usize).min(cols - 1);
        if cfg.axial_interpolation {
            // Linear (tent) weights between the two nearest row centres; clamped at the ends.
            let u = (dz / cell_z - 0.5).clamp(0.0, (rows - 1) as f64);
            let r0 = (u.floor() as usize).min(rows - 1);
            let r1 = (r0 + 1).min(rows - 1);
            let f = u - r0 as f64;
            sum[r0 * cols + c] += (1.0 - f) * q.s;
            weight[r0 * cols + c] += 1.0 - f;
            sum[r1 * cols + c] += f * q.s;
            weight[r1 * cols + c] += f;
        } else {
            let r = ((dz / cell_z) as usize).min(rows - 1);
            sum[r * cols + c] += q.s;
            weight[r * cols + c] += 1.0;
        }
    }
    // With tent weights one point spreads weight 1 over two rows; requiring half of
    // `min_points_per_cell` lets a single point observe (exactly) its nearer row, as it
    // observes its own row with box binning.
    let min_weight =
        cfg.min_points_per_cell.max(1) as f64 * if cfg.axial_interpolation { 0.5 } else { 1.0 };
    let mut observed = vec![false; rows * cols];
    for r in 0..rows {
        for (c, &masked_column) in masked.iter().enumerate().take(cols) {
            let i = r * cols + c;
            if weight[i] >= min_weight && !masked_column {
                observed[i] = true;
                sum[i] /= weight[i];
            } else {
                sum[i] = 0.0;
            }
        }
    }
    Descriptor {
        rows,
        cols,
        cell_z_m: cell_z,
        perimeter_m: contour.perimeter_m,
        offsets_m: sum.iter().map(|&v| v as f32).collect(),
        observed,
        normal_e1: columns.iter().map(|s| s.normal[0]).collect(),
        normal_e2: columns.iter().map(|s| s.normal[1]).collect(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::config::DecodConfig;

    #[test]
    fn cells_hold_mean_offsets_and_bottom_is_masked() {
        let cfg = DecodConfig::tunnel().descriptor;
        let contour = ReferenceContour::circle([0.0, 0.0], 3.0);
        let columns = column_samples(&contour, cfg.cols);
        let masked = bottom_mask(&columns, cfg.bottom_mask_deg);
        // +-30 deg of 256 columns: ~43 columns masked, symmetric about p = 0.
        let n_masked = masked.iter().filter(|&&m| m).count();
        assert!((42..=44).contains(&n_masked), "{n_masked}");
        assert_eq!(masked[0], masked[cfg.cols - 1]);
        let pts: Vec<ChartPoint> = (0..100_000)
            .map(|i| {
                let z = -2.5 + 5.0 * (i as f64 / 100_000.0);
                let p = (i as f64 * 0.618_033_988_7).fract();
                ChartPoint {
                    z: z + 1.0,
                    p,
                    s: 0.01 * p,
                }
            })
            .collect();
        let d = build_descriptor(&pts, 1.0, &contour, &columns, &masked, &cfg);
        let i = d.index(3, 128);
        assert!(d.observed[i]);
        assert!((d.offsets_m[i] - 0.01 * 128.5 / 256.0).abs() < 1e-4);
        assert!(!d.observed[d.index(3, 0)]);
        assert!((d.normal_e1[0] - 1.0).abs() < 1e-3 && (d.normal_e2[64] - 1.0).abs() < 1e-3);
    }

    #[test]
    fn axial_interpolation_splits_points_between_row_centres() {
        let mut cfg = DecodConfig::pipe().descriptor;
        cfg.axial_interpolation = true;
        let contour = ReferenceContour::circle([0.0, 0.0], 0.2);
        let columns = column_samples(&contour, cfg.cols);
        let masked = vec![false; cfg.cols];
        let cell = 2.0 * cfg.half_length_m / cfg.rows as f64;
        let row_centre = |r: usize| -cfg.half_length_m + (r as f64 + 0.5) * cell;
        let p = 100.5 / cfg.cols as f64;
        let pts = [
            // At the centre of row 4: all of its weight there.
            ChartPoint {
                z: row_centre(4),
                p,
                s: 0.002,
            },
            // A quarter cell above the centre of row 8: weight 3/4 on row 8, 1/4 on row 9.
            ChartPoint {
                z: row_centre(8) + 0.25 * cell,
                p,
                s: 0.004,
            },
            ChartPoint {
                z: row_centre(9),
                p,
                s: -0.004,
            },
        ];
        let d = build_descriptor(&pts, 0.0, &contour, &columns, &masked, &cfg);
        let at = |r: usize| d.offsets_m[d.index(r, 100)];
        assert!(d.observed[d.index(4, 100)] && (at(4) - 0.002).abs() < 1e-12);
        assert!(!d.observed[d.index(3, 100)] && !d.observed[d.index(5, 100)]);
        // Row 8 holds only the second point (weight 3/4 >= 1/2).
        assert!((at(8) - 0.004).abs() < 1e-12);
        // Row 9: (1/4 * 0.004 + 1 * -0.004) / (5/4).
        assert!((at(9) - (0.25 * 0.004 - 0.004) / 1.25).abs() < 1e-12);
    }
}
