//! Realistic synthetic descriptors for tests and benches (the extraction runs elsewhere).
//!
//! A joint's surface around its boundary is `s(z, p)` in metres:
//! - the joint groove: a Gaussian row at `z = 0` (sigma half a cell) whose depth varies
//!   subtly around the circumference (shared by every joint of one precast pipe);
//! - a joint-specific lip step for `z > 0` varying with `p` (per joint);
//! - wall roughness: a sum of random plane waves (wavelengths 1.5–8 cells along `z`,
//!   4–64 cycles per circumference), RMS `texture_m`, per joint;
//!
//! and an observation adds the nuisance terms of paper Eq. 2 (radius and ellipticity errors
//! `alpha(p)`, centring error `-(d1 n1 + d2 n2)`, axis tilt `z (beta1 n1 + beta2 n2)`), an
//! axial/circumferential misalignment of the origin, per-cell noise, the bottom ±30° sector
//! masked, optionally a missing arc of the circumference and random occlusion holes, and the
//! reversed heading. Surfaces are continuous functions, so misalignments may be sub-cell.

use std::f64::consts::TAU;

use crate::landmark::{Descriptor, Landmark};

/// A small deterministic generator (SplitMix64), so tests need no `rand` dependency.
#[derive(Clone, Debug)]
pub struct Rng(u64);

impl Rng {
    /// Seeded generator.
    pub fn new(seed: u64) -> Self {
        Self(seed ^ 0x9E37_79B9_7F4A_7C15)
    }
    /// Next 64 random bits.
    pub fn next_u64(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    }
    /// Uniform in `[0, 1)`.
    pub fn uniform(&mut self) -> f64 {
        (self.next_u64() >> 11) as f64 / (1u64 << 53) as f64
    }
    /// Uniform in `[lo, hi)`.
    pub fn range(&mut self, lo: f64, hi: f64) -> f64 {
        lo + (hi - lo) * self.uniform()
    }
    /// Standard normal (Box–Muller).
    pub fn normal(&mut self) -> f64 {
        let u1 = self.uniform().max(1e-300);
        let u2 = self.uniform();
        (-2.0 * u1.ln()).sqrt() * (TAU * u2).cos()
    }
}

/// The descriptor grid of a corridor.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Grid {
    /// Axial bins.
    pub rows: usize,
    /// Circumferential bins.
    pub cols: usize,
    /// Axial cell size, metres.
    pub cell_z_m: f64,
    /// Section radius, metres.
    pub radius_m: f64,
}

impl Grid {
    /// The tunnel preset's grid: 16 x 256 over ±2.4 m, a 3 m radius.
    pub fn tunnel() -> Self {
        Self {
            rows: 16,
            cols: 256,
            cell_z_m: 0.30,
            radius_m: 3.0,
        }
    }
    /// The pipe preset's grid: 16 x 256 over ±0.24 m, a 0.3 m radius.
    pub fn pipe() -> Self {
        Self {
            rows: 16,
            cols: 256,
            cell_z_m: 0.03,
            radius_m: 0.3,
        }
    }
}

/// Amplitudes of a corridor's surface, metres (defaults: a concrete tunnel, scaled by the
/// radius for pipes).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SurfaceParams {
    /// RMS of the wall roughness.
    pub texture_m: f64,
    /// Mean groove depth.
    pub groove_depth_m: f64,
    /// Relative circumferential variation of the groove depth.
    pub groove_variation: f64,
    /// RMS of the lip step across the joint.
    pub step_m: f64,
}

impl SurfaceParams {
    /// Tunnel-like amplitudes scaled to `grid.radius_m` (3 m: 2 mm roughness, 8 mm groove).
    pub fn for_grid(grid: &Grid) -> Self {
        let s = grid.radius_m / 3.0;
        Self {
            texture_m: 0.002 * s,
            groove_depth_m: 0.008 * s,
            groove_variation: 0.15,
            step_m: 0.001 * s,
        }
    }
}

#[derive(Clone, Debug)]
struct Wave {
    amp: f64,
    kz: f64, // radians per cell
    kp: f64, // cycles per circumference (integer: periodic)
    phase: f64,
}

/// One joint's surface (see the module docs).
#[derive(Clone, Debug)]
pub struct JointSurface {
    grid: Grid,
    params: SurfaceParams,
    texture: Vec<Wave>,
    groove: Vec<Wave>,
    step: Vec<Wave>,
}

fn waves(rng: &mut Rng, n: usize, kz: (f64, f64), kp: (f64, f64)) -> Vec<Wave> {
    let mut w: Vec<Wave> = (0..n)
        .map(|_| Wave {
            amp: rng.normal(),
            kz: TAU / rng.range(kz.0, kz.1) * if rng.uniform() < 0.5 { -1.0 } else { 1.0 },
            kp: rng.range(kp.0, kp.1).round(),
            phase: rng.range(0.0, TAU),
        })
        .collect();
    // Unit RMS: the waves are independent, each of RMS amp / sqrt(2).
    let rms = (w.iter().map(|w| w.amp * w.amp / 2.0).sum::<f64>())
        .sqrt()
        .max(1e-12);
    w.iter_mut().for_each(|w| w.amp /= rms);
    w
}

impl JointSurface {
    /// The joint `joint_seed` of the pipe `pipe_seed`: joints of one pipe share the groove
    /// geometry (precast), their roughness and lip step are their own. The same two seeds
    /// give the identical surface (an aliased joint).
    pub fn new(grid: Grid, params: SurfaceParams, pipe_seed: u64, joint_seed: u64) -> Self {
        let mut pipe = Rng::new(pipe_seed.wrapping_mul(0x1000_0001));
        let mut joint = Rng::new(joint_seed.wrapping_mul(0x2000_0003) ^ pipe_seed);
        Self {
            grid,
            params,
            groove: waves(&mut pipe, 4, (1e9, 1e9 + 1.0), (1.0, 6.0)),
            texture: waves(&mut joint, 48, (1.5, 8.0), (4.0, 64.0)),
            step: waves(&mut joint, 4, (1e9, 1e9 + 1.0), (1.0, 5.0)),
        }
    }

    /// Surface offset at axial position `z_cells` (cells from the boundary) and `p` in [0, 1).
    pub fn height(&self, z_cells: f64, p: f64) -> f64 {
        let sum = |ws: &[Wave]| -> f64 {
            ws.iter()
                .map(|w| w.amp * (w.kz * z_cells + TAU * w.kp * p + w.phase).sin())
                .sum()
        };
        let pr = &self.params;
        let depth = pr.groove_depth_m * (1.0 + pr.groove_variation * sum(&self.groove));
        let groove = -depth * (-0.5 * (z_cells / 0.5).powi(2)).exp();
        let step = pr.step_m * sum(&self.step) * 0.5 * (1.0 + (z_cells / 0.3).tanh());
        groove + step + pr.texture_m * sum(&self.texture)
    }

    /// One observation of this joint as a landmark (see [`Observation`]).
    pub fn observe(&self, obs: &Observation, noise_seed: u64) -> Landmark {
        let g = self.grid;
        let mut rng = Rng::new(noise_seed.wrapping_mul(0x3000_0005).wrapping_add(17));
        let mut offsets = self.observed_offsets(obs, &mut rng);
        let observed = observed_cells(g, obs, &mut rng);
        for (v, &o) in offsets.iter_mut().zip(&observed) {
            if !o {
                *v = 0.0;
            }
        }
        synthetic_landmark(
            g,
            obs.stamp,
            obs.shift_z_m,
            self.params.groove_depth_m,
            offsets,
            observed,
        )
    }

    /// The descriptor's offsets as `obs` sees them: the surface averaged over 2 x 2 samples
    /// per cell (a cell averages many points), the nuisance of the reference contour
    /// (radius, ellipticity, centring, tilt) and the cell noise; reversed for the other
    /// heading.
    fn observed_offsets(&self, obs: &Observation, rng: &mut Rng) -> Vec<f64> {
        let g = self.grid;
        let (rows, cols) = (g.rows, g.cols);
        let mut offsets = vec![0.0; rows * cols];
        for r in 0..rows {
            let z_cells = r as f64 + 0.5 - rows as f64 / 2.0;
            let z_m = z_cells * g.cell_z_m;
            for c in 0..cols {
                let p = (c as f64 + 0.5) / cols as f64;
                let mut h = 0.0;
                for (sz, sp) in [(-0.25, -0.25), (-0.25, 0.25), (0.25, -0.25), (0.25, 0.25)] {
                    h += 0.25
                        * self.height(
                            z_cells + sz + obs.shift_z_m / g.cell_z_m,
                            (p + sp / cols as f64 + obs.shift_p).rem_euclid(1.0),
                        );
                }
                let (n1, n2) = ((TAU * p).cos(), (TAU * p).sin());
                let nuisance = obs.radius_error_m + obs.ellipticity_m * (2.0 * TAU * p).cos()
                    - (obs.centring_m[0] * n1 + obs.centring_m[1] * n2)
                    + z_m * (obs.tilt[0] * n1 + obs.tilt[1] * n2);
                offsets[r * cols + c] = h + nuisance + obs.noise_m * rng.normal();
            }
        }
        if obs.reversed {
            offsets.reverse();
        }
        offsets
    }
}

/// Which cells `obs` observed, in the observer's frame (after the heading): not the masked
/// bottom sector, not the missing arc, not the random holes (`rng` after the offsets' noise).
fn observed_cells(g: Grid, obs: &Observation, rng: &mut Rng) -> Vec<bool> {
    let (rows, cols) = (g.rows, g.cols);
    let mut observed = vec![true; rows * cols];
    let bottom = obs.bottom_mask_deg / 360.0;
    for r in 0..rows {
        for c in 0..cols {
            let p = (c as f64 + 0.5) / cols as f64;
            let from_bottom = p.min(1.0 - p);
            let in_missing = obs
                .missing_arc
                .is_some_and(|(start, frac)| (p - start).rem_euclid(1.0) < frac);
            if from_bottom < bottom || in_missing {
                observed[r * cols + c] = false;
            }
        }
    }
    for _ in 0..obs.holes {
        let (r0, c0) = (
            (rng.uniform() * rows as f64) as usize,
            (rng.uniform() * cols as f64) as usize,
        );
        let (hr, hc) = (
            1 + (rng.uniform() * 3.0) as usize,
            4 + (rng.uniform() * 20.0) as usize,
        );
        for r in r0..(r0 + hr).min(rows) {
            for c in c0..c0 + hc {
                observed[r * cols + c % cols] = false;
            }
        }
    }
    observed
}

/// A landmark on a circular section of `g`'s radius, its boundary `shift_z_m` along the
/// submap's x axis, with the descriptor `offsets` / `observed`.
fn synthetic_landmark(
    g: Grid,
    stamp: f64,
    shift_z_m: f64,
    strength: f64,
    offsets: Vec<f64>,
    observed: Vec<bool>,
) -> Landmark {
    let cols = g.cols;
    let normal_e1: Vec<f64> = (0..cols)
        .map(|c| (TAU * (c as f64 + 0.5) / cols as f64).cos())
        .collect();
    let normal_e2: Vec<f64> = (0..cols)
        .map(|c| (TAU * (c as f64 + 0.5) / cols as f64).sin())
        .collect();
    let contour = normal_e1
        .iter()
        .zip(&normal_e2)
        .map(|(a, b)| [g.radius_m * a, g.radius_m * b])
        .collect();
    Landmark {
        submap_stamp: stamp,
        scan_stamps: (0..20).map(|k| stamp + 0.1 * k as f64).collect(),
        origin_in_submap: [shift_z_m, 0.0, 0.0],
        axis_in_submap: [1.0, 0.0, 0.0],
        e1_in_submap: [0.0, 0.0, -1.0],
        e2_in_submap: [0.0, 1.0, 0.0],
        contour_e1e2_m: contour,
        radius_m: g.radius_m,
        strength,
        descriptor: Descriptor {
            rows: g.rows,
            cols,
            cell_z_m: g.cell_z_m,
            perimeter_m: TAU * g.radius_m,
            offsets_m: offsets.iter().map(|&v| v as f32).collect(),
            observed,
            normal_e1,
            normal_e2,
        },
    }
}

/// How one joint is observed. `Default` is a clean forward view with realistic noise.
#[derive(Clone, Debug, PartialEq)]
pub struct Observation {
    /// Submap stamp, seconds (scan stamps follow it at 0.1 s).
    pub stamp: f64,
    /// Per-cell noise RMS, metres.
    pub noise_m: f64,
    /// Landmark origin displaced along the axis, metres (misalignment between views).
    pub shift_z_m: f64,
    /// Circumferential misalignment (gravity reference error), fraction of the circumference.
    pub shift_p: f64,
    /// Observed from the reversed heading.
    pub reversed: bool,
    /// Axis tilt `(beta1, beta2)`, metres of offset per metre of `z` per unit normal.
    pub tilt: [f64; 2],
    /// Contour centring error along `(e1, e2)`, metres.
    pub centring_m: [f64; 2],
    /// Contour radius error, metres.
    pub radius_error_m: f64,
    /// Contour ellipticity error, metres (`cos 2θ` term).
    pub ellipticity_m: f64,
    /// Bottom sector half-angle masked, degrees.
    pub bottom_mask_deg: f64,
    /// Missing arc `(start p, fraction of the circumference)`, e.g. an occluded half.
    pub missing_arc: Option<(f64, f64)>,
    /// Number of random occlusion holes (1–3 rows x 4–23 columns each).
    pub holes: usize,
}

impl Default for Observation {
    fn default() -> Self {
        Self {
            stamp: 0.0,
            noise_m: 0.0007,
            shift_z_m: 0.0,
            shift_p: 0.0,
            reversed: false,
            tilt: [0.0, 0.0],
            centring_m: [0.0, 0.0],
            radius_error_m: 0.0,
            ellipticity_m: 0.0,
            bottom_mask_deg: 30.0,
            missing_arc: None,
            holes: 3,
        }
    }
}

impl Observation {
    /// A random realistic view: noise, sub-cell misalignment, contour errors and holes drawn
    /// from `rng` (centring up to 3 cm and tilt up to 1° at a 3 m radius, scaled by the grid).
    pub fn random(grid: &Grid, stamp: f64, reversed: bool, rng: &mut Rng) -> Self {
        let s = grid.radius_m / 3.0;
        Self {
            stamp,
            shift_z_m: rng.range(-0.6, 0.6) * grid.cell_z_m,
            shift_p: rng.range(-1.5, 1.5) / grid.cols as f64,
            reversed,
            tilt: [rng.range(-0.015, 0.015), rng.range(-0.015, 0.015)],
            centring_m: [rng.range(-0.03, 0.03) * s, rng.range(-0.03, 0.03) * s],
            radius_error_m: rng.range(-0.02, 0.02) * s,
            ellipticity_m: rng.range(-0.01, 0.01) * s,
            holes: 2 + (rng.uniform() * 4.0) as usize,
            noise_m: 0.0007 * s,
            ..Self::default()
        }
    }
}
