//! Submaps (paper §III-A, §IV-A.2): consecutive scans accumulated with odometry into the body
//! frame of one anchor scan, then voxel-filtered. A submap is the unit of extraction; its
//! anchor stamp names the frame every landmark it yields is expressed in.

/// Voxel indices per axis lie in `[-VOXEL_INDEX_LIMIT, VOXEL_INDEX_LIMIT)`: the config refuses
/// a range window wider than that many voxels (`submap.max_range_m / submap.voxel_m`), so
/// the three indices pack into one `u64` (21 bits each).
pub const VOXEL_INDEX_LIMIT: i64 = 1 << 20;

/// The voxel of `q` as one `u64`: each index offset by `VOXEL_INDEX_LIMIT` into 21 bits, x
/// highest, so packed keys order like the `(x, y, z)` indices. The floor is a truncation
/// corrected below zero: the baseline x86-64 target has no rounding instruction, and a libm
/// call per coordinate took a tenth of the accumulation.
#[inline(always)]
fn voxel_key_of(x: f64, y: f64, z: f64, voxel: f64) -> u64 {
    let index = |v: f64| ((voxel_index(v, voxel) + VOXEL_INDEX_LIMIT) as u64) & 0x1F_FFFF;
    (index(x) << 42) | (index(y) << 21) | index(z)
}

/// `floor(v / voxel)` as a truncation corrected below zero (see [`voxel_key_of`]).
#[inline(always)]
pub(crate) fn voxel_index(v: f64, voxel: f64) -> i64 {
    let scaled = v / voxel;
    let t = scaled as i64;
    if (t as f64) > scaled { t - 1 } else { t }
}

/// Voxel keys packed from the range window alone, before any point is seen: every kept point
/// lies within `max_range_m` of the anchor, so each index fits `bits` bits above `lo`. The
/// packing keeps the `(x, y, z)` order of [`voxel_key_of`]; with the automatic configuration
/// (`max_range_m` about 256 voxels) it takes 30 bits, so points go straight into 16-byte rows
/// with no second pass to re-pack them.
struct WindowKeys {
    voxel: f64,
    lo: i64,
    bits: u32,
}

impl WindowKeys {
    fn new(voxel: f64, max_range: f64) -> Self {
        // One voxel of margin each side for the rounding of `v / voxel`.
        let reach = (max_range / voxel).ceil() as i64 + 1;
        let bits = 64 - ((2 * reach + 1) as u64).leading_zeros();
        Self {
            voxel,
            lo: -reach,
            bits,
        }
    }

    fn fits_u32(&self) -> bool {
        3 * self.bits <= u32::BITS
    }

    /// The key of `q`; an index outside the window (never for a kept point) is clamped.
    /// Computed in f64 to the end: the floor (`roundpd` where [`crate::accumulate`] runs it
    /// with SSE4.1 or later) is exact, so are the small integers after it, and adding 2^52
    /// puts an integer in `[0, 2^31)` into the low bits of the mantissa, so the conversion is
    /// a bit pattern rather than a scalar `cvttsd2si` per coordinate (AVX2 has no vector f64
    /// to integer conversion with Rust's saturation): the same indices as [`voxel_index`].
    #[inline(always)]
    fn key(&self, x: f64, y: f64, z: f64) -> u32 {
        const TWO_52: f64 = 4_503_599_627_370_496.0;
        let max = f64::from((1u32 << self.bits) - 1);
        let lo = self.lo as f64;
        let index = |v: f64| {
            let i = ((v / self.voxel).floor() - lo).clamp(0.0, max);
            (i + TWO_52).to_bits() as u32
        };
        (index(x) << (2 * self.bits)) | (index(y) << self.bits) | index(z)
    }
}

/// One point of a window on its way to the voxel filter: its voxel key and its position in
/// the anchor frame (f32: a micrometre at 10 m; the submap stores f32 centroids anyway).
type Keyed = (u64, [f32; 3]);

/// Voxel centroids of `rows` (keys from [`voxel_key_of`]), one per occupied voxel, in the
/// order of the voxel indices `(x, y, z)`.
///
/// The keys are re-packed relative to the window's own index range (a 64-beam window of
/// 0.6 M points spans ~500 voxels per axis: 3 digits instead of 6), radix-sorted, and each
/// run of equal keys averaged. A hash table of the window's voxels (with a write-combining
/// cache in front) took 45 % of the extraction's CPU on 64-beam logs: a spinning sensor puts
/// ~1.5 points into a voxel per scan, so nearly every point probed a table of ~100k voxels
/// out of cache; the sort's passes are sequential. Windows whose keys fit 32 bits from the
/// range window alone ([`WindowKeys`], every automatic configuration) never come here.
fn voxel_centroids(mut rows: Vec<Keyed>) -> Vec<[f32; 3]> {
    const SHIFTS: [u32; 3] = [42, 21, 0];
    let field = |k: u64, axis: usize| (k >> SHIFTS[axis]) & 0x1F_FFFF;
    let (mut lo, mut hi) = ([u64::MAX; 3], [0u64; 3]);
    for (k, _) in &rows {
        for axis in 0..3 {
            lo[axis] = lo[axis].min(field(*k, axis));
            hi[axis] = hi[axis].max(field(*k, axis));
        }
    }
    let bits: [u32; 3] = std::array::from_fn(|a| 64 - hi[a].saturating_sub(lo[a]).leading_zeros());
    for (k, _) in rows.iter_mut() {
        let c: [u64; 3] = std::array::from_fn(|a| field(*k, a) - lo[a]);
        *k = (c[0] << (bits[1] + bits[2])) | (c[1] << bits[2]) | c[2];
    }
    sorted_means(rows, bits.iter().sum())
}

/// The mean position of each run of equal keys, in order (sums in f64, in row order).
fn run_means<K: PartialEq>(rows: &[(K, [f32; 3])]) -> Vec<[f32; 3]> {
    let mut out = Vec::new();
    for run in rows.chunk_by(|a, b| a.0 == b.0) {
        let mut sum = [0.0f64; 3];
        for (_, q) in run {
            for axis in 0..3 {
                sum[axis] += f64::from(q[axis]);
            }
        }
        let n = run.len() as f64;
        out.push(sum.map(|v| (v / n) as f32));
    }
    out
}

/// [`run_means`] of `rows` sorted by the low `bits` bits of their keys ([`radix`]).
fn sorted_means<K: Copy + PartialEq + Into<u64>>(
    mut rows: Vec<(K, [f32; 3])>,
    bits: u32,
) -> Vec<[f32; 3]> {
    radix::sort_by_key(&mut rows, bits, |r| r.0.into());
    run_means(&rows)
}

use nalgebra::Vector3;

use crate::accumulate::accumulate;
use crate::config::SubmapConfig;
use crate::error::{DecodError, Result};
use crate::geometry::Pose;
use crate::radix;
use crate::scan::Scan;

/// Scans accumulated into the anchor scan's body frame.
#[derive(Clone, Debug)]
pub struct Submap {
    /// Stamp of the anchor scan, seconds: the submap's identity and frame.
    pub anchor_stamp: f64,
    /// Stamps of every scan accumulated, in time order (eligibility: no shared scans).
    pub scan_stamps: Vec<f64>,
    /// Odometry pose of the anchor scan (`T_world_anchor`).
    pub world_from_anchor: Pose,
    /// Voxel-filtered points in the anchor body frame, metres (one centroid per voxel).
    pub points_in_anchor: Vec<[f32; 3]>,
    /// Unit gravity direction (pointing down) in the anchor frame: the negated mean IMU
    /// specific force of the scans that have one, rotated into the anchor frame; the anchor's
    /// `-z` when no scan has an IMU reading.
    pub gravity_in_anchor: [f64; 3],
    /// Unit forward direction in the anchor frame: the sensor's `+x` axis of the anchor scan,
    /// i.e. always `[1, 0, 0]`. The sensor's heading, not the direction of motion, is used so
    /// that a crawler reversing out of a pipe (heading unchanged, motion backwards) keeps its
    /// axis orientation, while a vehicle that turns round flips it (paper §III-B headings).
    pub forward_in_anchor: [f64; 3],
}

impl Submap {
    /// Accumulates `scans` (time-ordered) into the frame of `scans[anchor_index]`.
    ///
    /// Motion compensation (paper §IV-A.2): each point of scan `k` goes to the anchor frame
    /// with `T_anchor_body_k = T_world_anchor^-1 T_world_body_k` from odometry. Points closer
    /// than `min_range_m` to their own sensor or farther than `max_range_m` from the anchor
    /// are dropped; the rest are voxel-filtered (one centroid per `voxel_m` cube).
    ///
    /// Errors name the scan and point: no scans, an anchor out of range, non-finite stamps or
    /// points, stamps out of order.
    pub fn from_scans(scans: &[Scan], anchor_index: usize, cfg: &SubmapConfig) -> Result<Self> {
        validate_scans(scans)?;
        Self::from_valid_scans(scans, anchor_index, cfg)
    }

    /// [`Self::from_scans`] of scans already validated (finite, in time order): a
    /// [`SubmapBuilder`]'s windows, whose every scan `push_window` checked (the check of
    /// every point again was 2 % of a 64-beam run's CPU).
    fn from_valid_scans(scans: &[Scan], anchor_index: usize, cfg: &SubmapConfig) -> Result<Self> {
        if scans.is_empty() {
            return Err(DecodError::invalid("scans", "no scans to accumulate"));
        }
        let anchor = scans.get(anchor_index).ok_or_else(|| {
            DecodError::invalid(
                "anchor_index",
                format!("{anchor_index} is out of range for {} scans", scans.len()),
            )
        })?;
        let anchor_from_world = anchor.world_from_body.inverse();
        let (voxel, max_range) = (cfg.voxel_m, cfg.max_range_m);
        let (min_r2, max_r2) = (cfg.min_range_m.powi(2), max_range.powi(2));
        let keys = WindowKeys::new(voxel, max_range);
        let (ranges, stride) = ((min_r2, max_r2), cfg.point_stride);
        let points_in_anchor = if keys.fits_u32() {
            let rows = accumulate(scans, &anchor_from_world, ranges, stride, |x, y, z| {
                keys.key(x, y, z)
            });
            sorted_means(rows, 3 * keys.bits)
        } else {
            let rows = accumulate(scans, &anchor_from_world, ranges, stride, |x, y, z| {
                voxel_key_of(x, y, z, voxel)
            });
            voxel_centroids(rows)
        };
        let mut force_sum = Vector3::zeros();
        let mut force_count = 0usize;
        for scan in scans {
            if let Some(f) = scan.specific_force_in_body {
                let anchor_from_body = (anchor_from_world * scan.world_from_body).to_homogeneous();
                let rotation = anchor_from_body.fixed_view::<3, 3>(0, 0).into_owned();
                force_sum += rotation * Vector3::from(f);
                force_count += 1;
            }
        }
        let gravity = if force_count > 0 && force_sum.norm() > 1e-9 {
            let g = -force_sum.normalize();
            [g.x, g.y, g.z]
        } else {
            [0.0, 0.0, -1.0]
        };
        Ok(Self {
            anchor_stamp: anchor.stamp,
            scan_stamps: scans.iter().map(|s| s.stamp).collect(),
            world_from_anchor: anchor.world_from_body,
            points_in_anchor,
            gravity_in_anchor: gravity,
            forward_in_anchor: [1.0, 0.0, 0.0],
        })
    }

    /// The submap of a builder's window ([`SubmapBuilder::push_window`]): anchored at its
    /// middle scan.
    pub fn from_window(window: &[Scan], cfg: &SubmapConfig) -> Result<Self> {
        Self::from_scans(window, window.len() / 2, cfg)
    }

    /// [`Self::from_window`] of a window a [`SubmapBuilder`] returned (its scans are
    /// validated as they are pushed).
    pub(crate) fn from_built_window(window: &[Scan], cfg: &SubmapConfig) -> Result<Self> {
        Self::from_valid_scans(window, window.len() / 2, cfg)
    }

    /// A submap made directly from points already in one frame (no odometry): for clouds
    /// that were accumulated elsewhere. `gravity` and `forward` need not be unit; they are
    /// normalised and must be finite and non-zero.
    pub fn from_points(
        stamp: f64,
        points: Vec<[f32; 3]>,
        gravity: [f64; 3],
        forward: [f64; 3],
    ) -> Result<Self> {
        if !stamp.is_finite() {
            return Err(DecodError::invalid("stamp", "must be finite"));
        }
        if let Some(i) = points.iter().position(|p| p.iter().any(|v| !v.is_finite())) {
            return Err(DecodError::invalid(
                "points",
                format!("row {i} is not finite: {:?}", points[i]),
            ));
        }
        Ok(Self {
            anchor_stamp: stamp,
            scan_stamps: vec![stamp],
            world_from_anchor: Pose::identity(),
            points_in_anchor: points,
            gravity_in_anchor: unit(gravity, "gravity")?,
            forward_in_anchor: unit(forward, "forward")?,
        })
    }
}

/// `v / |v|`, or an error naming `what` when `v` is zero or not finite.
pub(crate) fn unit(v: [f64; 3], what: &str) -> Result<[f64; 3]> {
    let n = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt();
    if !(n.is_finite() && n > 1e-12) {
        return Err(DecodError::invalid(
            what,
            format!("must be a finite non-zero vector, got {v:?}"),
        ));
    }
    Ok([v[0] / n, v[1] / n, v[2] / n])
}

fn validate_scans(scans: &[Scan]) -> Result<()> {
    let mut previous = f64::NEG_INFINITY;
    for (k, scan) in scans.iter().enumerate() {
        if !scan.stamp.is_finite() {
            return Err(DecodError::invalid(
                format!("scans[{k}].stamp"),
                "not finite",
            ));
        }
        if scan.stamp < previous {
            return Err(DecodError::invalid(
                format!("scans[{k}].stamp"),
                format!(
                    "{} is earlier than the previous scan ({previous})",
                    scan.stamp
                ),
            ));
        }
        previous = scan.stamp;
        if let Some(i) = scan
            .points_in_body
            .iter()
            .position(|p| p.iter().any(|v| !v.is_finite()))
        {
            return Err(DecodError::invalid(
                format!("scans[{k}].points[{i}]"),
                "not finite (NaN or inf)",
            ));
        }
        if let Some(f) = scan.specific_force_in_body
            && f.iter().any(|v| !v.is_finite())
        {
            return Err(DecodError::invalid(
                format!("scans[{k}].specific_force"),
                "not finite",
            ));
        }
    }
    Ok(())
}

/// Streams scans into submaps on the paper's schedule: a window of `scans_per_submap`
/// consecutive scans starts every `interval_s` (the paper: 20 scans every 8 s; both presets now use 2 s, see `src/config.rs`).
///
/// The anchor is the middle scan of the window (index `len / 2`): odometry error of the
/// motion compensation grows with the time from the anchor, so the middle halves the worst
/// case, and the submap extends both ways from the anchor. Memory is bounded by one window.
/// When a window takes longer than `interval_s` to fill, the next one starts at the first
/// scan after it (windows never overlap, so no scan is shared by two submaps).
/// With `max_travel_m` above 0, a window also closes, and the next one also starts, once
/// the odometry is that far from the window's first scan: the schedule holds its travel
/// per window where the robot drives faster than the speed it was chosen for.
#[derive(Debug)]
pub struct SubmapBuilder {
    cfg: SubmapConfig,
    window: Vec<Scan>,
    next_start_s: Option<f64>,
    /// Odometry position of the last window's first scan.
    start_position: Option<Vector3<f64>>,
    /// Windows `max_travel_m` closed before `scans_per_submap` scans.
    closed_by_travel: usize,
    last_stamp: f64,
}

impl SubmapBuilder {
    /// A builder with the submap section of the config.
    pub fn new(cfg: &SubmapConfig) -> Self {
        Self {
            cfg: cfg.clone(),
            window: Vec::with_capacity(cfg.scans_per_submap),
            next_start_s: None,
            start_position: None,
            closed_by_travel: 0,
            last_stamp: f64::NEG_INFINITY,
        }
    }

    /// Adds the next scan (time order); returns a submap when this scan completes a window.
    pub fn push(&mut self, scan: Scan) -> Result<Option<Submap>> {
        match self.push_window(scan)? {
            Some(window) => Submap::from_built_window(&window, &self.cfg).map(Some),
            None => Ok(None),
        }
    }

    /// Emits the partial window left at the end of the stream, if any (a short submap is
    /// still extracted; its size is in its `scan_stamps`).
    pub fn finish(&mut self) -> Result<Option<Submap>> {
        self.finish_window()
            .map(|window| Submap::from_built_window(&window, &self.cfg))
            .transpose()
    }

    /// [`Self::push`] without the accumulation: the window of scans when this scan completes
    /// one, for [`Submap::from_window`] to build later (the log processor builds a batch of
    /// them in parallel).
    pub fn push_window(&mut self, scan: Scan) -> Result<Option<Vec<Scan>>> {
        if !scan.stamp.is_finite() || scan.stamp < self.last_stamp {
            return Err(DecodError::invalid(
                "scan.stamp",
                format!(
                    "{} is not finite or earlier than the previous scan ({})",
                    scan.stamp, self.last_stamp
                ),
            ));
        }
        validate_scans(std::slice::from_ref(&scan))?;
        self.last_stamp = scan.stamp;
        if self.window.is_empty() {
            match self.next_start_s {
                Some(start) if scan.stamp < start && !self.travelled(&scan) => return Ok(None),
                _ => {
                    self.next_start_s = Some(scan.stamp + self.cfg.interval_s);
                    self.start_position = Some(scan.world_from_body.translation.vector);
                }
            }
        }
        let travelled = self.travelled(&scan);
        self.window.push(scan);
        if self.window.len() >= self.cfg.scans_per_submap {
            return Ok(self.finish_window());
        }
        if travelled {
            self.closed_by_travel += 1;
            return Ok(self.finish_window());
        }
        Ok(None)
    }

    /// How many windows `max_travel_m` closed before `scans_per_submap` scans (the robot
    /// faster than the speed the schedule was chosen for).
    pub fn closed_by_travel(&self) -> usize {
        self.closed_by_travel
    }

    /// Whether `scan` is `max_travel_m` or more from the last window's first scan.
    fn travelled(&self, scan: &Scan) -> bool {
        let limit = self.cfg.max_travel_m;
        limit > 0.0
            && self
                .start_position
                .is_some_and(|p| (scan.world_from_body.translation.vector - p).norm() >= limit)
    }

    /// [`Self::finish`] without the accumulation: the partial window, if any.
    pub fn finish_window(&mut self) -> Option<Vec<Scan>> {
        if self.window.is_empty() {
            return None;
        }
        let window = std::mem::replace(
            &mut self.window,
            Vec::with_capacity(self.cfg.scans_per_submap),
        );
        Some(window)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::config::DecodConfig;
    use nalgebra::{Point3, Translation3, UnitQuaternion};

    #[test]
    fn packed_voxel_keys_order_like_their_indices() {
        let voxel = 0.05;
        let points = [
            [-3.0, 2.0, 0.1],
            [-3.0, -2.0, 0.1],
            [0.0, 0.0, -0.01],
            [0.0, 0.0, 0.0],
            [4.99, -7.0, 3.0],
            [-51_000.0, 51_000.0, -51_000.0],
        ];
        let index = |p: &[f64; 3]| p.map(|v| (v / voxel).floor() as i64);
        for a in &points {
            for b in &points {
                let (ka, kb) = (
                    voxel_key_of(a[0], a[1], a[2], voxel),
                    voxel_key_of(b[0], b[1], b[2], voxel),
                );
                assert_eq!(ka.cmp(&kb), index(a).cmp(&index(b)), "{a:?} {b:?}");
            }
        }
    }

    #[test]
    fn a_range_window_too_wide_for_the_voxel_keys_is_refused() {
        let err = DecodConfig::from_toml_str(
            "[submap]\nvoxel_m = 0.0001\nmax_range_m = 200.0\n",
            crate::config::Preset::Tunnel,
        )
        .unwrap_err()
        .to_string();
        assert!(err.contains("submap.max_range_m"), "{err}");
    }

    fn scan(stamp: f64, x: f64, yaw: f64, points: Vec<[f32; 3]>) -> Scan {
        Scan {
            stamp,
            points_in_body: points,
            world_from_body: Pose::from_parts(
                Translation3::new(x, 0.0, 0.0),
                UnitQuaternion::from_euler_angles(0.0, 0.0, yaw),
            ),
            specific_force_in_body: Some([0.0, 0.0, 9.81]),
        }
    }

    #[test]
    fn points_are_motion_compensated_into_the_anchor_frame() {
        let mut cfg = DecodConfig::tunnel().submap;
        cfg.voxel_m = 0.01;
        // A world point at (5, 1, 0) seen from x = 0, 1, 2: all land on one voxel in anchor
        // frame (x = 1), at (4, 1, 0).
        let scans: Vec<Scan> = (0..3)
            .map(|k| scan(k as f64, k as f64, 0.0, vec![[5.0 - k as f32, 1.0, 0.0]]))
            .collect();
        let m = Submap::from_scans(&scans, 1, &cfg).unwrap();
        assert_eq!(m.points_in_anchor.len(), 1);
        let p = m.points_in_anchor[0];
        assert!(
            (p[0] - 4.0).abs() < 1e-5 && (p[1] - 1.0).abs() < 1e-5,
            "{p:?}"
        );
        assert_eq!(m.anchor_stamp, 1.0);
        assert!((m.gravity_in_anchor[2] + 1.0).abs() < 1e-12);
    }

    #[test]
    fn rotated_anchor_rotates_gravity_and_points() {
        let cfg = DecodConfig::tunnel().submap;
        let s = scan(0.0, 0.0, 0.3, vec![[2.0, 0.0, 0.0]]);
        let mut s2 = s.clone();
        s2.stamp = 0.1;
        s2.world_from_body = Pose::from_parts(
            Translation3::new(0.0, 0.0, 0.0),
            UnitQuaternion::from_euler_angles(0.2, 0.0, 0.3),
        );
        let m = Submap::from_scans(&[s, s2], 0, &cfg).unwrap();
        // Mean of gravity in both bodies, expressed in body 0: unit and still mostly down.
        let g = m.gravity_in_anchor;
        assert!(((g[0] * g[0] + g[1] * g[1] + g[2] * g[2]).sqrt() - 1.0).abs() < 1e-9);
        assert!(g[2] < -0.9 && g[1].abs() > 0.05, "{g:?}");
    }

    #[test]
    fn cached_accumulation_equals_the_plain_voxel_means() {
        // Three scans of 4,000 points in a spinning sensor's column order (beams within a
        // column, columns around), moved and turned: every voxel's centroid equals the mean
        // of its points computed directly (the cache only regroups the sums), and points
        // beyond the range window are dropped.
        // With a point stride, the same of every third point, from an offset that moves on
        // by one each scan.
        for max_range in [DecodConfig::tunnel().submap.max_range_m, 400.0] {
            for stride in [1, 3] {
                accumulation_equals_the_plain_voxel_means(max_range, stride);
            }
        }
    }

    /// With the tunnel preset's range window the keys take 3 x 10 bits (16-byte rows); with
    /// 400 m, 3 x 14 (the wide path).
    fn accumulation_equals_the_plain_voxel_means(max_range: f64, stride: usize) {
        let mut cfg = DecodConfig::tunnel().submap;
        cfg.voxel_m = 0.07;
        cfg.max_range_m = max_range;
        cfg.point_stride = stride;
        assert_eq!(
            WindowKeys::new(cfg.voxel_m, max_range).fits_u32(),
            max_range < 100.0
        );
        let column = |c: usize, b: usize| -> [f32; 3] {
            let az = c as f32 * 0.02;
            let el = (b as f32 - 8.0) * 0.03;
            let r = 2.0 + 0.5 * (c % 7) as f32 * 0.1 + if b == 3 { 200.0 } else { 0.0 };
            [
                r * az.cos() * el.cos(),
                r * az.sin() * el.cos(),
                r * el.sin(),
            ]
        };
        let points: Vec<[f32; 3]> = (0..250)
            .flat_map(|c| (0..16).map(move |b| column(c, b)))
            .collect();
        let scans: Vec<Scan> = (0..3)
            .map(|k| {
                scan(
                    k as f64 * 0.1,
                    0.03 * k as f64,
                    0.01 * k as f64,
                    points.clone(),
                )
            })
            .collect();
        let m = Submap::from_scans(&scans, 1, &cfg).unwrap();
        let anchor_from_world = scans[1].world_from_body.inverse();
        let mut reference: std::collections::BTreeMap<u64, ([f64; 3], u32)> =
            std::collections::BTreeMap::new();
        let mut kept = 0;
        for (k, s) in scans.iter().enumerate() {
            for (i, p) in s.points_in_body.iter().enumerate() {
                if i % stride != k % stride {
                    continue;
                }
                kept += 1;
                let body = Point3::new(p[0] as f64, p[1] as f64, p[2] as f64);
                let q = anchor_from_world * s.world_from_body * body;
                if body.coords.norm() < cfg.min_range_m || q.coords.norm() > cfg.max_range_m {
                    continue;
                }
                let e = reference
                    .entry(voxel_key_of(q.x, q.y, q.z, cfg.voxel_m))
                    .or_insert(([0.0; 3], 0));
                (0..3).for_each(|i| e.0[i] += q[i]);
                e.1 += 1;
            }
        }
        assert_eq!(kept, 3 * 4000 / stride); // three scans of 250 columns x 16 beams
        assert!(reference.len() > 500, "{}", reference.len());
        assert_eq!(m.points_in_anchor.len(), reference.len());
        for (got, (_, (sum, n))) in m.points_in_anchor.iter().zip(&reference) {
            for i in 0..3 {
                let want = sum[i] / f64::from(*n);
                // Rows hold f32 positions: 6e-8 relative each (1e-5 m at 200 m).
                assert!(
                    (f64::from(got[i]) - want).abs() < 1e-5 + 1e-7 * want.abs(),
                    "{got:?} {sum:?} {n}"
                );
            }
        }
    }

    #[test]
    fn voxel_means_agree_on_narrow_and_wide_keys() {
        // Keys spanning 3 x 5 bits and 3 x 13 bits (39 bits, beyond one u32 once re-packed),
        // several points per voxel in scrambled order: each centroid is its voxel's mean, in
        // key order, whatever the span.
        for span in [20u64, 6_000] {
            let mut state = 0x2545_F491_4F6C_DD1Du64;
            let mut next = || {
                state ^= state << 13;
                state ^= state >> 7;
                state ^= state << 17;
                state
            };
            let base = VOXEL_INDEX_LIMIT as u64 - span / 2;
            let mut rows: Vec<Keyed> = Vec::new();
            let mut reference: std::collections::BTreeMap<u64, ([f64; 3], f64)> =
                std::collections::BTreeMap::new();
            let voxels: Vec<u64> = (0..2_000)
                .map(|_| {
                    let idx = [next() % span, next() % span, next() % span].map(|i| base + i);
                    (idx[0] << 42) | (idx[1] << 21) | idx[2]
                })
                .collect();
            for _ in 0..20_000 {
                let key = voxels[(next() % 2_000) as usize];
                let q = [next() % 1000, next() % 1000, next() % 1000].map(|v| v as f32 * 1e-3);
                rows.push((key, q));
                let e = reference.entry(key).or_insert(([0.0; 3], 0.0));
                (0..3).for_each(|a| e.0[a] += f64::from(q[a]));
                e.1 += 1.0;
            }
            let got = voxel_centroids(rows);
            assert_eq!(got.len(), reference.len(), "span {span}");
            for (g, (sum, n)) in got.iter().zip(reference.values()) {
                for a in 0..3 {
                    assert!((f64::from(g[a]) - sum[a] / n).abs() < 1e-6, "{g:?} {sum:?}");
                }
            }
        }
    }

    #[test]
    fn bad_scans_are_named_errors() {
        let cfg = DecodConfig::tunnel().submap;
        let bad = scan(0.0, 0.0, 0.0, vec![[f32::NAN, 0.0, 0.0]]);
        let err = Submap::from_scans(&[bad], 0, &cfg).unwrap_err().to_string();
        assert!(err.contains("scans[0].points[0]"), "{err}");
        let a = scan(1.0, 0.0, 0.0, vec![]);
        let b = scan(0.5, 0.0, 0.0, vec![]);
        assert!(Submap::from_scans(&[a.clone(), b], 0, &cfg).is_err());
        assert!(Submap::from_scans(&[a], 3, &cfg).is_err());
        assert!(Submap::from_scans(&[], 0, &cfg).is_err());
    }

    #[test]
    fn builder_emits_on_schedule_with_middle_anchor() {
        let mut cfg = DecodConfig::tunnel().submap;
        cfg.scans_per_submap = 4;
        cfg.interval_s = 1.0;
        let mut b = SubmapBuilder::new(&cfg);
        let mut out = Vec::new();
        // Scans at 10 Hz over 3.05 s.
        for k in 0..31 {
            let t = k as f64 * 0.1;
            if let Some(m) = b.push(scan(t, t, 0.0, vec![[3.0, 0.0, 0.0]])).unwrap() {
                out.push(m);
            }
        }
        if let Some(m) = b.finish().unwrap() {
            out.push(m);
        }
        let anchors: Vec<f64> = out.iter().map(|m| m.anchor_stamp).collect();
        assert_eq!(out.len(), 4, "{anchors:?}");
        for (i, m) in out.iter().take(3).enumerate() {
            assert_eq!(m.scan_stamps.len(), 4);
            assert!((m.scan_stamps[0] - i as f64).abs() < 1e-9);
            assert!((m.anchor_stamp - (i as f64 + 0.2)).abs() < 1e-9);
        }
        assert_eq!(out[3].scan_stamps.len(), 1);
        assert!(b.push(scan(0.0, 0.0, 0.0, vec![])).is_err());
    }

    /// Windows at the speed the schedule was chosen for are the time schedule's; driving
    /// three times as fast, they close and start by the travel instead, one after another.
    #[test]
    fn builder_holds_the_travel_per_window_when_the_robot_speeds_up() {
        let mut cfg = DecodConfig::tunnel().submap;
        (cfg.scans_per_submap, cfg.interval_s) = (10, 1.0);
        let run = |cfg: &SubmapConfig| {
            let mut b = SubmapBuilder::new(cfg);
            let mut windows = Vec::new();
            // 10 Hz: 1 m/s for 4 s, then 3 m/s for 3 s.
            for k in 0..70 {
                let t = k as f64 * 0.1;
                let x = if t <= 4.0 { t } else { 4.0 + 3.0 * (t - 4.0) };
                windows.extend(b.push_window(scan(t, x, 0.0, vec![])).unwrap());
            }
            windows.extend(b.finish_window());
            windows
                .iter()
                .map(|w| (w[0].stamp, w.len()))
                .collect::<Vec<_>>()
        };
        let timed = run(&cfg);
        cfg.max_travel_m = 1.25;
        let both = run(&cfg);
        // The first four windows (1 m/s: 0.9 m each) are the time schedule's.
        assert_eq!(&both[..4], &timed[..4], "{both:?}");
        assert_eq!(timed.len(), 7, "{timed:?}");
        // At 3 m/s: 0.3 m a scan, closed at the fifth step (1.5 m), the next at the scan after.
        for pair in both[4..].windows(2) {
            let ((t0, n0), (t1, _)) = (pair[0], pair[1]);
            assert_eq!(n0, 6, "{both:?}");
            assert!((t1 - (t0 + 0.6)).abs() < 1e-9, "{both:?}");
        }
        assert!(both.len() >= 8, "{both:?}");
        cfg.max_travel_m = f64::NAN;
        let mut whole = DecodConfig::tunnel();
        whole.submap = cfg;
        let err = whole.validate().unwrap_err().to_string();
        assert!(err.contains("submap.max_travel_m"), "{err}");
    }
}
