//! Map consistency without ground truth (issue 13, `decod run --map`): how thick the wall is
//! where the outbound and the return pass overlap, per metre of corridor.
//!
//! A user with a real log has no ground truth, but the paper's own evidence on real pipes is
//! the map (Fig. 5): under odometry the two passes place the same wall at two positions;
//! after a correct loop closure they overlap. The figure measures that locally:
//!
//! 1. the map is cut into cubic *cells* (the caller's `cell_m`: 3 map voxels, 5 cm in the
//!    auto-scaled 0.3 m hume pipe, 0.5 m in a 3 m tunnel); a cell counts where both passes
//!    put at least [`MIN_CELL_POINTS`] points into it;
//! 2. in each such cell a plane is fitted to the points of both passes (least squares, the
//!    smallest principal axis as its normal): the wall, whatever the corridor's
//!    cross-section (circle, horseshoe, floor, segment seams and bolt pockets larger than a
//!    cell are all locally planar);
//! 3. the wall thickness of a bin (`bin_m` of chainage along the map's own outbound path) is
//!    the RMS distance of its points from their cell's plane, with each cell's
//!    [`PLANE_DOF`] fitted degrees of freedom taken out (`sqrt(sum r^2 / sum (n - 3))`,
//!    unbiased for the few points of a cell). Passes offset by `d` along the normal put their
//!    points `d / 2` either side of the common plane: thickness ~ `sqrt(noise^2 + d^2 / 4)`.
//!
//! The same fit on each pass alone in the same cells gives the *floor*: what the wall
//! measures when no second pass can disagree with it (the sensor's noise after the map's
//! voxel averaging, the wall's roughness within a cell, its curvature: ~`0.05 c^2 / r` for
//! cells of edge `c` on a radius `r`; and, within a pass, how well neighbouring submaps
//! agree).
//!
//! Why planes per cell and not one cross-section per metre: a tunnel's lining has seams,
//! bolt pockets and a flat invert that a per-sector median profile of a 3 m section cannot
//! follow; they made one pass alone 25 mm "thick" at 16.5 cm voxels, more than the passes
//! disagree, and the figure could not see the correction. Cells follow any shape at their
//! own scale.
//!
//! Everything comes from per-cell moments (count, sums, sums of outer products, taken about
//! the cell's corner so that no precision is lost far from the origin): the sum of squared
//! distances of a group's points from its least-squares plane is the smallest eigenvalue of
//! its scatter matrix, and from a plane of normal `u` through its centroid `u' S u`. One pass
//! over the points; memory is the cells, not the points.
//!
//! Limits: only the misalignment *across* the wall shows. In a uniform corridor an axial
//! offset moves the wall along itself (the degeneracy DeCOD exists for), so the figure is
//! blind to the axial error except where joints and features change the section. Passes more
//! than about half a cell apart fall into different cells and the figure saturates (it still
//! ranks maps, it no longer measures the offset). It complements ground truth; it does not
//! replace it.

use nalgebra::{Matrix3, Vector3};
use rustc_hash::FxHashMap;

use crate::error::{DecodError, Result};

/// Points of each pass for a cell to count (a plane has 3 degrees of freedom; one more
/// leaves a residual).
pub const MIN_CELL_POINTS: u32 = 4;
/// Points (of both passes, in counting cells) for a bin to get a figure: at ~9 points of
/// each pass per cell, about five cells.
pub const MIN_BIN_POINTS: u32 = 100;
/// Fitted degrees of freedom per plane (offset and two tilts).
pub const PLANE_DOF: f64 = 3.0;
/// Most bins a figure may hold (1,000 km of corridor at 1 m bins): a bound on the allocation
/// for chainages that are not a corridor's.
pub const MAX_BINS: usize = 1_000_000;

/// Where one submap's points are measured along the corridor: the path sample nearest to the
/// submap's anchor (`origin`), the path's unit `tangent` there and its `arclength` (metres
/// from the path's start).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ChainageFrame {
    /// Path sample, metres.
    pub origin: [f64; 3],
    /// Unit tangent of the path at the sample.
    pub tangent: [f64; 3],
    /// Path length from the start to the sample, metres.
    pub arclength: f64,
}

/// Wall thickness per bin (module docs), metres; NaN where the passes do not both reach.
#[derive(Clone, Debug, PartialEq)]
pub struct Thickness {
    /// Chainage of the first bin's start, metres (a multiple of the bin length).
    pub start_m: f64,
    /// Both passes about their common planes, per bin.
    pub overlap_m: Vec<f64>,
    /// Each pass about its own planes in the same cells (the floor): outbound, return.
    pub floor_m: [Vec<f64>; 2],
}

/// Chainage of each point (metres along the path): the arclength of its submap's frame plus
/// its offset along that frame's tangent. Linear within a submap's reach; `submap[i]` indexes
/// `frames`.
pub fn point_chainage(
    points: &[[f64; 3]],
    submap: &[u32],
    frames: &[ChainageFrame],
) -> Result<Vec<f64>> {
    same_length("submap", submap.len(), points.len())?;
    points
        .iter()
        .zip(submap)
        .enumerate()
        .map(|(i, (p, &k))| {
            let f = frames.get(k as usize).ok_or_else(|| {
                DecodError::invalid(
                    format!("submap[{i}]"),
                    format!("{k} is not one of the {} submap frames", frames.len()),
                )
            })?;
            let along: f64 = (0..3).map(|a| (p[a] - f.origin[a]) * f.tangent[a]).sum();
            Ok(f.arclength + along)
        })
        .collect()
}

/// Moments of one pass's points in one cell, about the cell's corner: count, sums and the
/// six distinct sums of products (`xx xy xz yy yz zz`; a symmetric 3 x 3 stored whole took
/// 216 instead of 168 bytes per cell, ~50 MB more on a 1 km tunnel's map).
#[derive(Clone, Copy, Debug, Default)]
struct Moments {
    count: u32,
    sum: Vector3<f64>,
    outer: [f64; 6],
}

impl Moments {
    fn add(&mut self, p: Vector3<f64>) {
        self.count += 1;
        self.sum += p;
        let products = [
            p.x * p.x,
            p.x * p.y,
            p.x * p.z,
            p.y * p.y,
            p.y * p.z,
            p.z * p.z,
        ];
        for (o, v) in self.outer.iter_mut().zip(products) {
            *o += v;
        }
    }

    fn merged(&self, other: &Moments) -> Moments {
        Moments {
            count: self.count + other.count,
            sum: self.sum + other.sum,
            outer: std::array::from_fn(|k| self.outer[k] + other.outer[k]),
        }
    }

    /// Scatter matrix about the centroid.
    fn scatter(&self) -> Matrix3<f64> {
        let n = f64::from(self.count.max(1));
        let [xx, xy, xz, yy, yz, zz] = self.outer;
        Matrix3::new(xx, xy, xz, xy, yy, yz, xz, yz, zz) - self.sum * self.sum.transpose() / n
    }
}

/// One cell: the moments of each pass and the sum of its points' chainage.
#[derive(Clone, Copy, Debug, Default)]
struct Cell {
    pass: [Moments; 2],
    chainage_sum: f64,
}

/// Smallest eigenvalue of a symmetric 3 x 3 matrix and its unit eigenvector, in closed form:
/// the trigonometric solution of the characteristic cubic, the vector as the largest cross
/// product of two rows of `a - lambda I`. Several times faster than the iterative solver on
/// the tens of thousands of cells of a map, and exact to rounding (unit-tested against it).
fn smallest_eigen(a: Matrix3<f64>) -> (f64, Vector3<f64>) {
    let q = a.trace() / 3.0;
    let b = a - Matrix3::identity() * q;
    let p = (b.norm_squared() / 6.0).sqrt();
    if p <= f64::MIN_POSITIVE {
        // A multiple of the identity: every direction is an eigenvector.
        return (q, Vector3::z());
    }
    let r = ((b / p).determinant() / 2.0).clamp(-1.0, 1.0);
    let value = q + 2.0 * p * (r.acos() / 3.0 + 2.0 * std::f64::consts::PI / 3.0).cos();
    let rows = a - Matrix3::identity() * value;
    let (r0, r1, r2) = (
        rows.row(0).transpose(),
        rows.row(1).transpose(),
        rows.row(2).transpose(),
    );
    let crosses = [r0.cross(&r1), r0.cross(&r2), r1.cross(&r2)];
    let best = crosses
        .iter()
        .copied()
        .max_by(|x, y| x.norm_squared().total_cmp(&y.norm_squared()))
        .unwrap_or_else(Vector3::z);
    let norm = best.norm();
    if norm > 0.0 {
        (value, best / norm)
    } else {
        (value, Vector3::z())
    }
}

/// Sums of squared residuals and of degrees of freedom per bin.
#[derive(Clone, Debug)]
struct BinSums {
    ss: Vec<f64>,
    dof: Vec<f64>,
}

impl BinSums {
    fn new(n: usize) -> Self {
        Self {
            ss: vec![0.0; n],
            dof: vec![0.0; n],
        }
    }

    fn add(&mut self, bin: usize, ss: f64, points: u32) {
        self.ss[bin] += ss;
        self.dof[bin] += f64::from(points) - PLANE_DOF;
    }

    /// `sqrt(sum ss / sum dof)` per bin, NaN without degrees of freedom or where `counted`
    /// falls short of [`MIN_BIN_POINTS`].
    fn rms(&self, counted: &[u32]) -> Vec<f64> {
        self.ss
            .iter()
            .zip(&self.dof)
            .zip(counted)
            .map(|((&ss, &dof), &n)| {
                if dof > 0.0 && n >= MIN_BIN_POINTS {
                    (ss.max(0.0) / dof).sqrt()
                } else {
                    f64::NAN
                }
            })
            .collect()
    }
}

/// Checks the inputs of [`wall_thickness`]; returns the chainage range.
fn check_inputs(
    points: &[[f64; 3]],
    pass: &[u8],
    chainage: &[f64],
    cell_m: f64,
    bin_m: f64,
) -> Result<(f64, f64)> {
    for (name, v) in [("cell_m", cell_m), ("bin_m", bin_m)] {
        if !(v.is_finite() && v > 0.0) {
            return Err(DecodError::invalid(
                name,
                format!("must be finite and > 0, got {v}"),
            ));
        }
    }
    same_length("pass", pass.len(), points.len())?;
    same_length("chainage", chainage.len(), points.len())?;
    if let Some(i) = pass.iter().position(|&p| p > 1) {
        let why = format!("{} is not a pass (0 outbound, 1 return)", pass[i]);
        return Err(DecodError::invalid(format!("pass[{i}]"), why));
    }
    let bad = |p: &[f64; 3], c: f64| !(c.is_finite() && p.iter().all(|v| v.is_finite()));
    if let Some(i) = (0..points.len()).find(|&i| bad(&points[i], chainage[i])) {
        let why = format!("not finite: {:?} at chainage {}", points[i], chainage[i]);
        return Err(DecodError::invalid(format!("points[{i}]"), why));
    }
    let lo = chainage.iter().copied().fold(f64::INFINITY, f64::min);
    let hi = chainage.iter().copied().fold(f64::NEG_INFINITY, f64::max);
    Ok((lo, hi))
}

fn same_length(name: &str, got: usize, points: usize) -> Result<()> {
    if got == points {
        return Ok(());
    }
    Err(DecodError::invalid(
        name,
        format!("has {got} entries for {points} points"),
    ))
}

/// The cells of a map (module docs, step 1), in order of first appearance.
fn cells(points: &[[f64; 3]], pass: &[u8], chainage: &[f64], cell_m: f64) -> Vec<Cell> {
    // A cell holds ~9 map points (0.32 M points in 36k cells on a 20 m pe map): reserve that.
    let expected = points.len() / 8;
    let mut index: FxHashMap<[i64; 3], u32> =
        FxHashMap::with_capacity_and_hasher(expected, Default::default());
    let mut cells: Vec<Cell> = Vec::with_capacity(expected);
    for ((p, &which), &c) in points.iter().zip(pass).zip(chainage) {
        // Saturating casts: a point a billion cells out lands in an edge cell, never panics.
        let key = p.map(|v| (v / cell_m).floor() as i64);
        let corner = Vector3::from_fn(|a, _| key[a] as f64 * cell_m);
        let local = Vector3::new(p[0], p[1], p[2]) - corner;
        let next = cells.len();
        let at = *index.entry(key).or_insert(next as u32) as usize;
        if at == next {
            cells.push(Cell::default());
        }
        let cell = &mut cells[at];
        cell.pass[usize::from(which)].add(local);
        cell.chainage_sum += c;
    }
    cells
}

/// Wall thickness per `bin_m` of chainage where both passes of a map reach, and each pass's
/// own floor (module docs), in cells of edge `cell_m`. `points` (N) metres, `pass` 0
/// outbound / 1 return, `chainage` metres along the outbound path ([`point_chainage`]).
pub fn wall_thickness(
    points: &[[f64; 3]],
    pass: &[u8],
    chainage: &[f64],
    cell_m: f64,
    bin_m: f64,
) -> Result<Thickness> {
    let (lo, hi) = check_inputs(points, pass, chainage, cell_m, bin_m)?;
    if points.is_empty() {
        let floor_m = [Vec::new(), Vec::new()];
        return Ok(Thickness {
            start_m: 0.0,
            overlap_m: Vec::new(),
            floor_m,
        });
    }
    let start_m = (lo / bin_m).floor() * bin_m;
    let span = ((hi - start_m) / bin_m).floor();
    if span >= MAX_BINS as f64 {
        return Err(DecodError::invalid(
            "chainage",
            format!("spans {lo} to {hi} m: more than {MAX_BINS} bins of {bin_m} m"),
        ));
    }
    let n = span as usize + 1;
    let mut overlap = BinSums::new(n);
    let mut floors = [BinSums::new(n), BinSums::new(n)];
    let mut counted = vec![0u32; n];
    for cell in cells(points, pass, chainage, cell_m) {
        let [out, ret] = &cell.pass;
        if out.count < MIN_CELL_POINTS || ret.count < MIN_CELL_POINTS {
            continue;
        }
        let both = out.merged(ret);
        let mean = cell.chainage_sum / f64::from(both.count);
        let bin = (((mean - start_m) / bin_m).floor().max(0.0) as usize).min(n - 1);
        let scatter = [out.scatter(), ret.scatter()];
        for (p, s) in scatter.iter().enumerate() {
            floors[p].add(bin, smallest_eigen(*s).0, cell.pass[p].count);
        }
        // Both passes about one plane through their common centroid, normal to the pooled
        // scatter of the passes about their own centroids. (A plane fitted to all points at
        // once could tilt through two parallel patches that sit side by side in the cell and
        // hide their offset; the pooled scatter cannot.)
        let (_, normal) = smallest_eigen(scatter[0] + scatter[1]);
        let ss = (normal.transpose() * both.scatter() * normal)[(0, 0)];
        overlap.add(bin, ss, both.count);
        counted[bin] += both.count;
    }
    Ok(Thickness {
        start_m,
        overlap_m: overlap.rms(&counted),
        floor_m: [floors[0].rms(&counted), floors[1].rms(&counted)],
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Deterministic pseudo-random numbers in [0, 1) (a 64-bit LCG's top bits).
    struct Lcg(u64);

    impl Lcg {
        fn next(&mut self) -> f64 {
            self.0 = self
                .0
                .wrapping_mul(6_364_136_223_846_793_005)
                .wrapping_add(1_442_695_040_888_963_407);
            (self.0 >> 11) as f64 / (1u64 << 53) as f64
        }

        /// Approximately normal (sum of 12 uniforms), unit variance.
        fn normal(&mut self) -> f64 {
            (0..12).map(|_| self.next()).sum::<f64>() - 6.0
        }
    }

    /// Two passes over a flat wall z = 0 (10 m x 1 m), the return pass lifted by `offset`,
    /// noise `noise` m; chainage = x.
    fn two_walls(offset: f64, noise: f64) -> (Vec<[f64; 3]>, Vec<u8>, Vec<f64>) {
        let mut rng = Lcg(7);
        let (mut points, mut pass, mut chainage) = (Vec::new(), Vec::new(), Vec::new());
        for which in 0..2u8 {
            for _ in 0..40_000 {
                let x = 10.0 * rng.next();
                let z = noise * rng.normal() + if which == 1 { offset } else { 0.0 };
                points.push([x, rng.next(), z + 0.01]);
                pass.push(which);
                chainage.push(x);
            }
        }
        (points, pass, chainage)
    }

    fn median(v: &[f64]) -> f64 {
        let mut ok: Vec<f64> = v.iter().copied().filter(|x| x.is_finite()).collect();
        ok.sort_by(f64::total_cmp);
        ok[ok.len() / 2]
    }

    #[test]
    fn thickness_is_the_noise_when_passes_agree_and_half_their_offset_otherwise() {
        let noise = 0.002;
        let (p, s, c) = two_walls(0.0, noise);
        let t = wall_thickness(&p, &s, &c, 0.1, 1.0).unwrap();
        assert_eq!(t.overlap_m.len(), 10);
        assert!(t.overlap_m.iter().all(|v| v.is_finite()));
        // 4,000 points per bin and pass: the RMS is within a few per cent of the noise.
        assert!((median(&t.overlap_m) / noise - 1.0).abs() < 0.05);
        for floor in &t.floor_m {
            assert!((median(floor) / noise - 1.0).abs() < 0.05);
        }
        // Offset d: points d/2 either side of the common plane.
        let d = 0.01;
        let (p, s, c) = two_walls(d, noise);
        let t = wall_thickness(&p, &s, &c, 0.1, 1.0).unwrap();
        let expected = (noise * noise + d * d / 4.0).sqrt();
        assert!((median(&t.overlap_m) / expected - 1.0).abs() < 0.05);
        // The floors do not see the other pass.
        assert!((median(&t.floor_m[1]) / noise - 1.0).abs() < 0.05);
    }

    #[test]
    fn one_pass_alone_has_no_overlap_and_bins_follow_the_chainage() {
        let (p, s, c) = two_walls(0.0, 0.001);
        let half = p.len() / 2;
        let t = wall_thickness(&p[..half], &s[..half], &c[..half], 0.1, 1.0).unwrap();
        assert!(t.overlap_m.iter().all(|v| v.is_nan()));
        let shifted: Vec<f64> = c.iter().map(|x| x - 3.5).collect();
        let t = wall_thickness(&p, &s, &shifted, 0.1, 1.0).unwrap();
        assert_eq!(t.start_m, -4.0);
        assert_eq!(t.overlap_m.len(), 11);
        assert!(t.overlap_m[0].is_finite() && t.overlap_m[10].is_finite());
    }

    #[test]
    fn bad_inputs_are_refused_by_name() {
        let (p, s, c) = two_walls(0.0, 0.001);
        let err = |r: Result<Thickness>| r.unwrap_err().to_string();
        assert!(err(wall_thickness(&p, &s, &c, 0.0, 1.0)).contains("cell_m"));
        assert!(err(wall_thickness(&p, &s[1..], &c, 0.1, 1.0)).contains("pass"));
        let mut s2 = s.clone();
        s2[5] = 2;
        assert!(err(wall_thickness(&p, &s2, &c, 0.1, 1.0)).contains("pass[5]"));
        let mut p2 = p.clone();
        p2[9][1] = f64::NAN;
        assert!(err(wall_thickness(&p2, &s, &c, 0.1, 1.0)).contains("points[9]"));
        let mut c2 = c.clone();
        c2[0] = -1e12;
        assert!(err(wall_thickness(&p, &s, &c2, 0.1, 1.0)).contains("bins"));
        let empty = wall_thickness(&[], &[], &[], 0.1, 1.0).unwrap();
        assert!(empty.overlap_m.is_empty());
    }

    #[test]
    fn closed_form_eigen_matches_the_iterative_solver() {
        let mut rng = Lcg(3);
        for scale in [1e-6, 1e-3, 1.0, 1e3] {
            for _ in 0..200 {
                let m = Matrix3::from_fn(|_, _| scale * (rng.next() - 0.5));
                // Flat scatters (a wall: one small eigenvalue) as well as round ones.
                let a = m * m.transpose() + Matrix3::from_diagonal(&Vector3::new(scale, 0.0, 0.0));
                let (value, vector) = smallest_eigen(a);
                let eigen = nalgebra::SymmetricEigen::new(a);
                let min = eigen.eigenvalues.min();
                // Exact to ~1e-10 of the largest eigenvalue (the cubic's arccos near +-1):
                // a wall's residuals are 1e-3-1e-2 of its scatter, so 1e-7 of the figure.
                let size = a.norm();
                assert!((value - min).abs() <= 1e-9 * size, "{value} vs {min}");
                let residual = (a * vector - vector * value).norm();
                assert!(residual <= 1e-6 * size, "residual {residual}");
                assert!((vector.norm() - 1.0).abs() < 1e-12);
            }
        }
        let (value, _) = smallest_eigen(Matrix3::identity() * 2.0);
        assert_eq!(value, 2.0);
    }

    #[test]
    fn chainage_runs_along_each_submaps_tangent() {
        let frames = [
            ChainageFrame {
                origin: [0.0; 3],
                tangent: [1.0, 0.0, 0.0],
                arclength: 0.0,
            },
            ChainageFrame {
                origin: [5.0, 0.0, 0.0],
                tangent: [0.0, 1.0, 0.0],
                arclength: 5.0,
            },
        ];
        let points = [[2.0, 7.0, 1.0], [5.0, 3.0, 9.0]];
        let c = point_chainage(&points, &[0, 1], &frames).unwrap();
        assert_eq!(c, vec![2.0, 8.0]);
        let e = point_chainage(&points, &[0, 2], &frames)
            .unwrap_err()
            .to_string();
        assert!(e.contains("submap[1]"), "{e}");
    }
}
