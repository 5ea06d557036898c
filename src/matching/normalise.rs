//! Nuisance normalisation of a descriptor (paper §III-B, Eq. 2).
//!
//! Contour estimation errors distort every offset systematically: a centring error
//! `(d1, d2)` adds `-(d1 n1(p) + d2 n2(p))`, a radius or shape error adds a function of `p`,
//! an axial profile (the joint groove itself, a radius change along the axis) adds a function
//! of `z`, and an axis tilt adds `z (beta1 n1(p) + beta2 n2(p))`. The model
//! `f(z, p) = alpha(p) + gamma(z) + z (beta1 n1(p) + beta2 n2(p))` is fitted by least squares
//! over the observed cells and subtracted; what remains is the surface texture that tells
//! boundaries apart.
//!
//! Solving: `alpha` has one unknown per observed column and enters each cell with weight 1,
//! so it is eliminated exactly (column-wise centring, a Schur complement); the remaining 18
//! unknowns (`gamma` per row, `beta1`, `beta2`) are solved from their normal equations with
//! faer's Cholesky. Gauge freedom: `alpha(p) + c`, `gamma(z) - c` fit equally well; it is fixed
//! by `sum gamma = 0`, imposed by adding `u u^T` (`u` = ones on the `gamma` block) to the
//! normal matrix, which leaves the residual unchanged because `u` spans its null space. Rows
//! with no observed cell get a tiny ridge so the system stays definite (their `gamma` is 0).

//!
//! Ablations measured on 50 synthetic joints x 2 random views (tunnel grid, return traversal
//! reversed; `matching::tests::ablations_run_and_verification_keeps_precision`):
//! five-variable precision 1.00 / recall 0.98; scale-only 0 accepted (the contour errors,
//! up to 3 cm of centring against 2 mm of texture, dominate every patch); sign-only
//! 1.00 / 0.98 (the z-scored patches already discard amplitude); without verification
//! 0.58 / 0.58 with all 50 queries accepted.

use faer::linalg::matmul::matmul;
use faer::linalg::solvers::Solve;
use faer::{Accum, Mat, Par, Side};

use crate::config::MatchingConfig;
use crate::landmark::Descriptor;

/// Which normalisation `MatchingConfig::normalisation` selects.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Normalisation {
    /// Eq. 2, five-variable model (the paper).
    FiveVariable,
    /// Ablation: subtract the mean and divide by the RMS over observed cells (scale only).
    ScaleOnly,
    /// Raw offsets.
    None,
}

impl Normalisation {
    /// From the config string (validated by `DecodConfig::validate`; unknown means the paper's).
    pub fn from_config(cfg: &MatchingConfig) -> Self {
        match cfg.normalisation.as_str() {
            "scale_only" => Normalisation::ScaleOnly,
            "none" => Normalisation::None,
            _ => Normalisation::FiveVariable,
        }
    }
}

/// The normalised field of `descriptor`, row-major `rows x cols`, 0.0 at unobserved cells.
/// `sign_only` (ablation) keeps only the sign of each normalised offset.
pub fn normalised_field(d: &Descriptor, mode: Normalisation, sign_only: bool) -> Vec<f64> {
    let mut field = match mode {
        Normalisation::FiveVariable => five_variable_residual(d),
        Normalisation::ScaleOnly => scale_only(d),
        Normalisation::None => masked(d, |_, v| v),
    };
    if sign_only {
        for (v, &o) in field.iter_mut().zip(&d.observed) {
            *v = if !o || *v == 0.0 { 0.0 } else { v.signum() };
        }
    }
    field
}

fn masked(d: &Descriptor, f: impl Fn(usize, f64) -> f64) -> Vec<f64> {
    d.offsets_m
        .iter()
        .zip(&d.observed)
        .enumerate()
        .map(|(i, (&v, &o))| if o { f(i, f64::from(v)) } else { 0.0 })
        .collect()
}

fn scale_only(d: &Descriptor) -> Vec<f64> {
    let n = d.observed_count().max(1) as f64;
    let obs = || {
        d.offsets_m
            .iter()
            .zip(&d.observed)
            .filter(|(_, o)| **o)
            .map(|(&v, _)| f64::from(v))
    };
    let mean = obs().sum::<f64>() / n;
    let rms = (obs().map(|v| (v - mean).powi(2)).sum::<f64>() / n).sqrt();
    let scale = if rms > 0.0 { 1.0 / rms } else { 1.0 };
    masked(d, |_, v| (v - mean) * scale)
}

/// Masked Gaussian smoothing of a normalised `field` along `p` only (row-major
/// `rows x cols`, circular in `p`, sigma in columns): normalised convolution
/// `G * (m F) / G * m`. Returns the smoothed field and its mask: a cell is observed when at
/// least half of the kernel weight around it was observed, so isolated empty cells between
/// observed ones are filled and the edges of large gaps (the masked bottom sector) stay put;
/// unobserved cells hold 0. `sigma <= 0` returns the inputs unchanged.
///
/// Why (the paper is silent): a cell holds the mean of the few points that fell in it. Where
/// points are sparse (a 4.9 mm x 30 mm cell on a 0.4 m pipe gets a handful of returns at
/// 1.5 mm range noise, and ~40 % of the cells get none, in stripes along the axis) the
/// cell-to-cell noise exceeds the texture, keypoints land on noise maxima, and two sparse
/// masks rarely leave half of a patch mutually observed, so most patch distances are
/// infinite. Joint texture varies smoothly around the circumference (groove depth, width
/// and centre harmonics, lip eccentricity, chips centimetres of arc wide) but sharply along
/// the axis (a groove fills one or two rows), so only `p` is smoothed. Measured on the
/// simulated `pe` pipe (groove rows, best shift): the correlation of two views of the same
/// coupler rose from 0.25 (raw) to 0.50 at sigma 4 columns while different couplers stayed
/// at 0.19; with the pipe preset (1 cm of arc = 2 columns, z tent binning) well-observed
/// same-coupler pairs (> 55 % of cells observed) went from median K 3 to 9, different
/// couplers stayed at K <= 5.
pub fn smooth_along_p(
    field: &[f64],
    observed: &[bool],
    rows: usize,
    cols: usize,
    sigma: f64,
) -> (Vec<f64>, Vec<bool>) {
    if sigma <= 0.0 || cols == 0 {
        return (field.to_vec(), observed.to_vec());
    }
    let half = ((3.0 * sigma).ceil() as usize).min(cols / 2);
    let kernel: Vec<f64> = (0..=half)
        .map(|k| (-((k * k) as f64) / (2.0 * sigma * sigma)).exp())
        .collect();
    let total: f64 = kernel[0] + 2.0 * kernel[1..].iter().sum::<f64>();
    let mut out = vec![0.0; rows * cols];
    let mut mask = vec![false; rows * cols];
    // Each row padded circularly by `half` cells each side, so the taps need no modulo
    // (two integer divisions per tap were most of the smoothing's time); the sums run in
    // the same order as before: centre, then +k and -k outwards.
    let mut f = vec![0.0; cols + 2 * half];
    let mut m = vec![false; cols + 2 * half];
    for r in 0..rows {
        for (k, (fv, mv)) in f.iter_mut().zip(m.iter_mut()).enumerate() {
            let cc = r * cols + (k + cols - half) % cols;
            (*fv, *mv) = (field[cc], observed[cc]);
        }
        for c in 0..cols {
            let (mut n, mut d) = (0.0, 0.0);
            let centre = c + half;
            for (k, w) in kernel.iter().enumerate() {
                let mut add = |cc: usize| {
                    if m[cc] {
                        n += w * f[cc];
                        d += w;
                    }
                };
                add(centre + k);
                if k > 0 {
                    add(centre - k);
                }
            }
            if d >= 0.5 * total {
                out[r * cols + c] = n / d;
                mask[r * cols + c] = true;
            }
        }
    }
    (out, mask)
}

/// Axial coordinate of row `r`'s centre relative to the landmark origin, metres.
#[inline]
pub fn row_z_m(d: &Descriptor, r: usize) -> f64 {
    (r as f64 + 0.5 - d.rows as f64 / 2.0) * d.cell_z_m
}

/// Residual of the least-squares fit of Eq. 2 over observed cells (see the module docs).
pub fn five_variable_residual(d: &Descriptor) -> Vec<f64> {
    let means = ColumnMeans::of(d);
    let (m, b) = normal_equations(d, &means);
    let theta = solve_gauged(m, &b, d.rows);
    residual(d, &means, &theta)
}

/// Per column over its observed cells: the count, the mean offset, and the mean of the
/// regressors besides alpha (`e_r`, `z n1(c)`, `z n2(c)`; `k = rows + 2` per column). Alpha
/// is eliminated by centring each column.
struct ColumnMeans {
    n: Vec<usize>,
    y: Vec<f64>,
    g: Vec<f64>,
    k: usize,
}

impl ColumnMeans {
    fn of(d: &Descriptor) -> Self {
        let (rows, cols) = (d.rows, d.cols);
        let k = rows + 2; // gamma per row, beta1, beta2
        let mut col_n = vec![0usize; cols];
        let mut col_y = vec![0.0; cols];
        let mut col_g = vec![0.0; cols * k];
        for r in 0..rows {
            let z = row_z_m(d, r);
            for c in 0..cols {
                let i = d.index(r, c);
                if d.observed[i] {
                    col_n[c] += 1;
                    col_y[c] += f64::from(d.offsets_m[i]);
                    let g = &mut col_g[c * k..(c + 1) * k];
                    g[r] += 1.0;
                    g[rows] += z * d.normal_e1[c];
                    g[rows + 1] += z * d.normal_e2[c];
                }
            }
        }
        for c in 0..cols {
            if col_n[c] > 0 {
                let inv = 1.0 / col_n[c] as f64;
                col_y[c] *= inv;
                col_g[c * k..(c + 1) * k].iter_mut().for_each(|x| *x *= inv);
            }
        }
        Self {
            n: col_n,
            y: col_y,
            g: col_g,
            k,
        }
    }
}

/// The normal equations `(m, b)` of the column-centred problem:
/// `sum_cells (g - gbar_c)(g - gbar_c)^T = sum_cells g g^T - sum_c n_c gbar_c gbar_c^T`.
/// The first sum is sparse (`g = e_r + z n1 e_b1 + z n2 e_b2`): per-row sums. The second is
/// one GEMM, `G^T G` with the rows of `G = sqrt(n_c) gbar_c` (cols x k), likewise for `b`.
fn normal_equations(d: &Descriptor, means: &ColumnMeans) -> (Mat<f64>, Mat<f64>) {
    let (rows, cols, k) = (d.rows, d.cols, means.k);
    let (col_n, col_y, col_g) = (&means.n, &means.y, &means.g);
    let (mut row_cnt, mut row_t1, mut row_t2, mut row_y) = (
        vec![0.0; rows],
        vec![0.0; rows],
        vec![0.0; rows],
        vec![0.0; rows],
    );
    let (mut s11, mut s12, mut s22, mut b1, mut b2) = (0.0, 0.0, 0.0, 0.0, 0.0);
    for r in 0..rows {
        let z = row_z_m(d, r);
        let row = r * cols..(r + 1) * cols;
        for (((&o, &y), &n1), &n2) in d.observed[row.clone()]
            .iter()
            .zip(&d.offsets_m[row])
            .zip(&d.normal_e1)
            .zip(&d.normal_e2)
        {
            if o {
                let y = f64::from(y);
                let (t1, t2) = (z * n1, z * n2);
                row_cnt[r] += 1.0;
                row_t1[r] += t1;
                row_t2[r] += t2;
                row_y[r] += y;
                s11 += t1 * t1;
                s12 += t1 * t2;
                s22 += t2 * t2;
                b1 += t1 * y;
                b2 += t2 * y;
            }
        }
    }
    let mut m = Mat::<f64>::zeros(k, k);
    let mut b = Mat::<f64>::zeros(k, 1);
    for r in 0..rows {
        m[(r, r)] = row_cnt[r];
        m[(r, rows)] = row_t1[r];
        m[(rows, r)] = row_t1[r];
        m[(r, rows + 1)] = row_t2[r];
        m[(rows + 1, r)] = row_t2[r];
        b[(r, 0)] = row_y[r];
    }
    m[(rows, rows)] = s11;
    m[(rows, rows + 1)] = s12;
    m[(rows + 1, rows)] = s12;
    m[(rows + 1, rows + 1)] = s22;
    b[(rows, 0)] = b1;
    b[(rows + 1, 0)] = b2;
    let sqrt_n: Vec<f64> = col_n.iter().map(|&n| (n as f64).sqrt()).collect();
    let g = Mat::<f64>::from_fn(cols, k, |c, a| sqrt_n[c] * col_g[c * k + a]);
    let gy = Mat::<f64>::from_fn(cols, 1, |c, _| sqrt_n[c] * col_y[c]);
    matmul(
        m.as_mut(),
        Accum::Add,
        g.transpose(),
        g.as_ref(),
        -1.0,
        Par::Seq,
    );
    matmul(
        b.as_mut(),
        Accum::Add,
        g.transpose(),
        gy.as_ref(),
        -1.0,
        Par::Seq,
    );
    (m, b)
}

/// `theta` (gamma per row, beta1, beta2) from the normal equations, with the gauge
/// `sum gamma = 0` (`u u^T` on the gamma block) and a ridge for empty rows and for a
/// degenerate tilt column (e.g. all rows but one unobserved); non-finite entries are 0.
fn solve_gauged(mut m: Mat<f64>, b: &Mat<f64>, rows: usize) -> Vec<f64> {
    let k = m.nrows();
    let trace: f64 = (0..k).map(|a| m[(a, a)]).sum::<f64>().max(1e-300);
    let ridge = 1e-10 * trace / k as f64;
    for a in 0..rows {
        for bb in 0..rows {
            m[(a, bb)] += trace / k as f64 / rows as f64;
        }
    }
    for a in 0..k {
        m[(a, a)] += ridge;
    }
    let theta = match m.llt(Side::Lower) {
        Ok(llt) => llt.solve(b),
        Err(_) => m.partial_piv_lu().solve(b),
    };
    (0..k)
        .map(|a| theta[(a, 0)])
        .map(|t| if t.is_finite() { t } else { 0.0 })
        .collect()
}

/// The observed offsets minus the fitted five-variable surface (0 where unobserved).
fn residual(d: &Descriptor, means: &ColumnMeans, theta: &[f64]) -> Vec<f64> {
    let (rows, cols, k) = (d.rows, d.cols, means.k);
    // alpha_c = column mean of y minus the column mean of the other terms.
    let alpha: Vec<f64> = (0..cols)
        .map(|c| {
            let mean_other: f64 = means.g[c * k..(c + 1) * k]
                .iter()
                .zip(theta)
                .map(|(a, t)| a * t)
                .sum();
            means.y[c] - mean_other
        })
        .collect();
    let (b1, b2) = (theta[rows], theta[rows + 1]);
    let mut out = vec![0.0; rows * cols];
    for r in 0..rows {
        let z = row_z_m(d, r);
        for c in 0..cols {
            let i = d.index(r, c);
            if d.observed[i] {
                let fit = alpha[c] + theta[r] + z * (b1 * d.normal_e1[c] + b2 * d.normal_e2[c]);
                out[i] = f64::from(d.offsets_m[i]) - fit;
            }
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    fn descriptor(rows: usize, cols: usize, f: impl Fn(f64, usize) -> f64) -> Descriptor {
        let tau = std::f64::consts::TAU;
        let n1: Vec<f64> = (0..cols)
            .map(|c| (tau * (c as f64 + 0.5) / cols as f64).cos())
            .collect();
        let n2: Vec<f64> = (0..cols)
            .map(|c| (tau * (c as f64 + 0.5) / cols as f64).sin())
            .collect();
        let mut d = Descriptor {
            rows,
            cols,
            cell_z_m: 0.3,
            perimeter_m: 18.0,
            offsets_m: vec![0.0; rows * cols],
            observed: vec![true; rows * cols],
            normal_e1: n1,
            normal_e2: n2,
        };
        for r in 0..rows {
            for c in 0..cols {
                let z = row_z_m(&d, r);
                let i = d.index(r, c);
                d.offsets_m[i] = f(z, c) as f32;
                // Bottom sector and a hole unobserved.
                d.observed[i] = !(c < cols / 12 || c > cols - cols / 12 || (r < 3 && c > 100));
            }
        }
        d
    }

    #[test]
    fn removes_the_nuisance_model_exactly() {
        let cols = 256;
        let tau = std::f64::consts::TAU;
        let nuisance = |z: f64, c: usize| {
            let p = (c as f64 + 0.5) / cols as f64;
            let (n1, n2) = ((tau * p).cos(), (tau * p).sin());
            0.004 * (3.0 * tau * p).sin() + 0.01 * z * z - 0.02 * n1 + 0.003 * z * n1
                - 0.002 * z * n2
                + 0.05
        };
        let d = descriptor(16, cols, nuisance);
        let field = five_variable_residual(&d);
        let max = field.iter().fold(0.0f64, |m, v| m.max(v.abs()));
        // Exact model: only rounding error remains, that of the offsets' f32 (half an ulp is
        // 7.5e-9 m for the largest here, 0.14 m; a term the model missed would leave mm).
        assert!(max < 2e-8, "residual {max}");
    }

    #[test]
    fn keeps_texture_orthogonal_to_the_model() {
        let cols = 256;
        // A checkerboard-like interaction term is not representable by Eq. 2.
        let texture = |z: f64, c: usize| 0.001 * (z * 7.0).sin() * ((c as f64) * 0.3).cos();
        let d = descriptor(16, cols, texture);
        let field = five_variable_residual(&d);
        let energy = |v: &[f64]| v.iter().map(|x| x * x).sum::<f64>();
        let raw: Vec<f64> = masked(&d, |_, v| v);
        let kept = energy(&field) / energy(&raw);
        assert!(kept > 0.8, "kept {kept}");
    }

    #[test]
    fn smoothing_along_p_denoises_fills_small_gaps_and_keeps_large_ones() {
        let (rows, cols) = (4, 128);
        let tau = std::f64::consts::TAU;
        // Smooth texture (3rd harmonic, 1 mm) plus alternating +-1 mm cell noise; every
        // fifth column empty, columns 100..128 a large gap.
        let truth = |c: usize| 0.001 * (3.0 * tau * c as f64 / cols as f64).sin();
        let mut field = vec![0.0; rows * cols];
        let mut observed = vec![false; rows * cols];
        for r in 0..rows {
            for c in 0..100 {
                if c % 5 != 4 {
                    let noise = if (r + c) % 2 == 0 { 0.001 } else { -0.001 };
                    field[r * cols + c] = truth(c) + noise;
                    observed[r * cols + c] = true;
                }
            }
        }
        let (out, mask) = smooth_along_p(&field, &observed, rows, cols, 2.0);
        // Interior gap cells are filled; deep inside the large gap nothing is invented.
        assert!(mask[cols + 49] && mask[cols + 50]);
        assert!(!mask[cols + 114]);
        // Away from the large gap the +-1 mm cell noise (RMS 1 mm) mostly cancels: the
        // pattern is alternating except across the empty columns, and a sigma-2 Gaussian
        // leaves the 3rd harmonic (wavelength 43 columns) within 5 %, so the RMS error must
        // drop below a third of the noise.
        let rms = ((10..90)
            .map(|c| (out[cols + c] - truth(c)).powi(2))
            .sum::<f64>()
            / 80.0)
            .sqrt();
        assert!(rms < 3e-4, "RMS error {rms}");
        // Off means unchanged.
        let (same, same_mask) = smooth_along_p(&field, &observed, rows, cols, 0.0);
        assert_eq!(same, field);
        assert_eq!(same_mask, observed);
    }
}
