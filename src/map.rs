//! The run's point-cloud map (issue 13, `decod run --map`): every submap's voxel-filtered
//! cloud kept in a bounded voxel map during the stream, so that once the pose graph has
//! corrected the trajectory the same points can be placed by the corrected poses (and by
//! the odometry, for comparison) without reading the log again.
//!
//! **Layout.** Submaps are grouped into *segments*: consecutive submaps whose anchors travel
//! at most `segment_length_m` (odometry path length) from the segment's first anchor, the
//! segment's *reference*. A segment stores one voxel per `voxel_m` cube in the reference's
//! odometry frame: the centroid of the points that fell into it, their count, and the first
//! submap that saw it. Overlapping submaps (a slow crawler anchors a submap every few
//! centimetres of travel, each seeing a metre ahead) thus share voxels, and memory grows with
//! the distance travelled (times `(segment_length_m + 2 max_range_m) / segment_length_m`,
//! the overlap of neighbouring segments), not with the duration of the log or the number of
//! scans: a robot standing still adds nothing once its segment's rows are merged.
//!
//! **Placement.** A voxel is placed by the pose of the submap that first saw it:
//! `T_world_anchor(k) * T_odom_anchor(k)^-1 * T_odom_reference * centroid`, where
//! `T_world_anchor(k)` is the trajectory being rendered (corrected or odometry). This is the
//! submap placed by its own pose; points of a later submap of the same segment that fell
//! into the same voxel move with it (they are within one voxel of it in the odometry frame).
//! [`SegmentMap::render`] merges the placed voxels of every segment into one voxel grid per
//! pass (outbound / return), so a wall seen on both passes appears twice when the passes
//! disagree and once, overlapping, when they agree (the paper's Fig. 5).

use nalgebra::{Point3, Vector3};
use rayon::prelude::*;

use crate::error::{DecodError, Result};
use crate::geometry::Pose;
use crate::radix;

/// Map voxel edge as a multiple of the submap voxel (`submap.voxel_m`): 0.054 r under the
/// auto configuration (~115 points round the circumference), 16.5 mm under the pipe preset,
/// 0.16 m under the tunnel preset. Each map voxel averages about 9 wall points of a submap
/// (a surface: 3 x 3 submap voxels). Measured on the 15 m hume pipe (issue 13): a factor 2
/// gave 2.2x the points and made map, figure and recording 50 % of the run's time; 3 keeps
/// them within the 20 % budget, and the wall-thickness figure (centroids, per pass) changed
/// by < 0.1 mm.
pub const MAP_VOXEL_FACTOR: f64 = 3.0;

/// Segment length as a multiple of the submap reach (`submap.max_range_m`). Memory is at
/// most `(L + 2 R) / L` = 2 times the map; measured: the voxels held are 1.5-1.6 times the
/// rendered map's points (both passes) on the simulated hume, pe and shield runs of
/// `python -m decod_rs.bench.visuals`. The segment that holds the turnaround mixes at most
/// `R` of each pass, where the two passes' odometry still agree.
pub const SEGMENT_REACH_FACTOR: f64 = 2.0;

/// Every `POINT_STRIDE`-th point of a submap goes into the map. A map voxel holds ~9 submap
/// points of each submap that sees it (3 x 3 on the surface) and each wall voxel is seen by
/// several submaps, so every fourth point still reaches every voxel (unit-tested on a dense
/// wall); streaming with the map costs +13-16 % of the stream's time at stride 2 (best of 5,
/// `python -m decod_rs.bench.visuals`), about half that at 4.
pub const POINT_STRIDE: usize = 4;

/// One stored voxel, in its segment's reference frame.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct MapVoxel {
    /// Centroid of the points that fell into the voxel, metres, reference frame.
    pub centroid: [f32; 3],
    /// Number of (submap) points merged.
    pub count: u32,
    /// Index (in insertion order) of the first submap that saw the voxel.
    pub first_submap: u32,
}

/// A closed segment: its reference submap and its voxels (sorted by voxel key).
#[derive(Clone, Debug)]
struct Segment {
    reference: u32,
    voxels: Vec<MapVoxel>,
}

/// One voxel of one submap: the sum and count of the submap's points in it.
#[derive(Clone, Copy, Debug)]
struct SubmapVoxel {
    key: [i32; 3],
    sum: [f64; 3],
    count: u32,
    submap: u32,
}

/// The segment being filled: each submap's voxels, appended in submap order and merged (one
/// row per voxel) when the segment closes, or before, whenever the rows have doubled since the
/// last merge (a robot standing still adds a submap's voxels again and again, but never
/// closes its segment). A hash table of the segment's voxels, probed once per submap voxel,
/// missed the cache on nearly every probe: half of the map's CPU on the pe pipe with 64
/// beams (780,000 voxels); sorting and merging reads the rows in order.
#[derive(Debug)]
struct OpenSegment {
    reference: u32,
    reference_from_world: Pose,
    travelled_m: f64,
    last_position: Vector3<f64>,
    rows: Vec<SubmapVoxel>,
    /// Rows after the last merge.
    merged: usize,
}

/// Rows an open segment holds before its first merge.
const MERGE_MIN_ROWS: usize = 1 << 16;

impl OpenSegment {
    fn push_submap(&mut self, voxels: impl Iterator<Item = SubmapVoxel>) {
        self.rows.extend(voxels);
        if self.rows.len() > MERGE_MIN_ROWS.max(2 * self.merged) {
            self.merge();
        }
    }

    fn merge(&mut self) {
        merge_rows(&mut self.rows);
        self.merged = self.rows.len();
    }

    fn close(mut self) -> Segment {
        self.merge();
        let voxels = self
            .rows
            .iter()
            .map(|row| {
                let n = f64::from(row.count.max(1));
                MapVoxel {
                    centroid: row.sum.map(|v| (v / n) as f32),
                    count: row.count,
                    first_submap: row.submap,
                }
            })
            .collect();
        Segment {
            reference: self.reference,
            voxels,
        }
    }
}

/// `rows` merged into one row per voxel, in key order: the sums added in row order (the same
/// additions, in the same order, however often rows are merged: a segment's rows are appended
/// in submap order), the submap the first row's (the earliest that saw the voxel).
fn merge_rows(rows: &mut Vec<SubmapVoxel>) {
    sort_by_voxel(rows);
    let mut out = 0;
    for i in 0..rows.len() {
        let row = rows[i];
        if out > 0 && rows[out - 1].key == row.key {
            let cell = &mut rows[out - 1];
            for (s, v) in cell.sum.iter_mut().zip(row.sum) {
                *s += v;
            }
            cell.count = cell.count.saturating_add(row.count);
        } else {
            // Summed from zero like the others (0 + -0 is +0).
            let sum = row.sum.map(|v| 0.0 + v);
            rows[out] = SubmapVoxel { sum, ..row };
            out += 1;
        }
    }
    rows.truncate(out);
}

/// Stable sort of `rows` by voxel key `(x, y, z)`: a radix sort of the keys re-packed
/// relative to their own range (a segment spans a few thousand voxels per axis), or, when the
/// range needs 64 bits or more (a corrupt point kilometres away), a comparison sort.
fn sort_by_voxel(rows: &mut Vec<SubmapVoxel>) {
    let (mut lo, mut hi) = ([i32::MAX; 3], [i32::MIN; 3]);
    for row in rows.iter() {
        for axis in 0..3 {
            lo[axis] = lo[axis].min(row.key[axis]);
            hi[axis] = hi[axis].max(row.key[axis]);
        }
    }
    let span = |a: usize| u64::from(hi[a].abs_diff(lo[a]));
    let bits: [u32; 3] = std::array::from_fn(|a| 64 - span(a).leading_zeros());
    // Below 64 bits in all, so that every shift below is by less than 64.
    if rows.is_empty() || bits.iter().sum::<u32>() >= u64::BITS {
        rows.sort_by_key(|r| r.key);
        return;
    }
    let offset = |r: &SubmapVoxel, a: usize| u64::from(r.key[a].abs_diff(lo[a]));
    radix::sort_by_key(rows, bits.iter().sum(), |r| {
        (offset(r, 0) << (bits[1] + bits[2])) | (offset(r, 1) << bits[2]) | offset(r, 2)
    });
}

/// A map rendered by a trajectory: one point per (pass, voxel), sorted by pass then voxel.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct MapCloud {
    /// Point positions in the world frame of the trajectory, metres.
    pub points: Vec<[f64; 3]>,
    /// Pass of each point (the caller's labels, e.g. 0 outbound, 1 return).
    pub pass: Vec<u8>,
    /// The first submap that saw each point (smallest index merged into it).
    pub first_submap: Vec<u32>,
    /// Submap points merged into each point.
    pub count: Vec<u32>,
}

/// A voxel placed in the world: its sort key ([`placed_key`]: pass, then world voxel), the
/// count-weighted sum of its position, its count and its first submap.
type PlacedVoxel = (u128, [f64; 3], u32, u32);

/// One map point per run of equal keys in `placed` (sorted by key): the count-weighted mean
/// of the run's world positions, its pass, its first submap and its point count.
fn merge_runs(placed: &[PlacedVoxel]) -> MapCloud {
    let mut out = MapCloud::default();
    let mut rest = placed;
    while let Some(first) = rest.first() {
        let run = rest.iter().take_while(|p| p.0 == first.0).count();
        let (cell, tail) = rest.split_at(run);
        rest = tail;
        let mut sum = [0.0; 3];
        let mut count = 0u64;
        for p in cell {
            sum[0] += p.1[0];
            sum[1] += p.1[1];
            sum[2] += p.1[2];
            count += u64::from(p.2);
        }
        let n = count.max(1) as f64;
        out.points.push([sum[0] / n, sum[1] / n, sum[2] / n]);
        out.pass.push((first.0 >> 96) as u8);
        out.first_submap
            .push(cell.iter().map(|p| p.3).min().unwrap_or(first.3));
        out.count.push(u32::try_from(count).unwrap_or(u32::MAX));
    }
    out
}

/// `(pass, key)` packed into one integer that sorts like the tuple (each `i32` with its sign
/// bit flipped sorts like the signed value): one integer comparison per step of the sort
/// instead of four, a quarter less CPU for the whole render on the pe pipe's 300,000 voxels.
fn placed_key(pass: u8, key: [i32; 3]) -> u128 {
    let unsigned = |v: i32| u128::from((v as u32) ^ 0x8000_0000);
    (u128::from(pass) << 96)
        | (unsigned(key[0]) << 64)
        | (unsigned(key[1]) << 32)
        | unsigned(key[2])
}

/// The bounded voxel map of a run (module docs).
#[derive(Debug)]
pub struct SegmentMap {
    voxel_m: f64,
    segment_length_m: f64,
    submap_stamps: Vec<f64>,
    odom_from_submap: Vec<Pose>,
    segments: Vec<Segment>,
    open: Option<OpenSegment>,
    /// Every how many points of a submap are added (1 = all).
    point_stride: usize,
    /// A submap's rows on their way into the segment, reused (its capacity is kept).
    scratch: Vec<SubmapVoxel>,
}

impl SegmentMap {
    /// An empty map with voxel edge `voxel_m` and segments of `segment_length_m` of travel;
    /// both must be finite and positive.
    pub fn new(voxel_m: f64, segment_length_m: f64) -> Result<Self> {
        for (name, v) in [("voxel_m", voxel_m), ("segment_length_m", segment_length_m)] {
            if !(v.is_finite() && v > 0.0) {
                return Err(DecodError::invalid(
                    name,
                    format!("must be finite and > 0, got {v}"),
                ));
            }
        }
        Ok(Self {
            voxel_m,
            segment_length_m,
            submap_stamps: Vec::new(),
            odom_from_submap: Vec::new(),
            segments: Vec::new(),
            open: None,
            point_stride: 1,
            scratch: Vec::new(),
        })
    }

    /// The map for a run with this submap voxel and reach: [`MAP_VOXEL_FACTOR`],
    /// [`SEGMENT_REACH_FACTOR`] and [`POINT_STRIDE`] applied.
    pub fn for_submaps(submap_voxel_m: f64, max_range_m: f64) -> Result<Self> {
        let mut map = Self::new(
            MAP_VOXEL_FACTOR * submap_voxel_m,
            SEGMENT_REACH_FACTOR * max_range_m,
        )?;
        map.point_stride = POINT_STRIDE;
        Ok(map)
    }

    /// Adds a submap: its anchor stamp, odometry pose `T_odom_anchor` and voxel-filtered
    /// points in the anchor frame. Non-finite points are skipped. Submaps get indices in the
    /// order they are added ([`Self::submap_stamps`]).
    pub fn add_submap(&mut self, stamp: f64, odom_from_anchor: &Pose, points: &[[f32; 3]]) {
        let index = self.submap_stamps.len() as u32;
        let position = odom_from_anchor.translation.vector;
        if let Some(open) = self.open.as_mut() {
            open.travelled_m += (position - open.last_position).norm();
            open.last_position = position;
        }
        if self
            .open
            .as_ref()
            .is_some_and(|open| open.travelled_m > self.segment_length_m)
        {
            self.close_open();
        }
        let open = self.open.get_or_insert_with(|| OpenSegment {
            reference: index,
            reference_from_world: odom_from_anchor.inverse(),
            travelled_m: 0.0,
            last_position: position,
            rows: Vec::new(),
            merged: 0,
        });
        let reference_from_anchor = open.reference_from_world * odom_from_anchor;
        let inv = 1.0 / self.voxel_m;
        // The submap's points merged into one row per voxel, then appended to the segment.
        let rows = &mut self.scratch;
        rows.clear();
        rows.extend(points.iter().step_by(self.point_stride).filter_map(|p| {
            let q = reference_from_anchor
                * Point3::new(f64::from(p[0]), f64::from(p[1]), f64::from(p[2]));
            let key = voxel_key(&q.coords, inv)?;
            Some(SubmapVoxel {
                key,
                sum: [q.x, q.y, q.z],
                count: 1,
                submap: index,
            })
        }));
        merge_rows(rows);
        open.push_submap(rows.drain(..));
        self.submap_stamps.push(stamp);
        self.odom_from_submap.push(*odom_from_anchor);
    }

    /// Closes the segment being filled (after the last submap; adding more starts a new one).
    pub fn finish(&mut self) {
        self.close_open();
    }

    fn close_open(&mut self) {
        if let Some(open) = self.open.take() {
            self.segments.push(open.close());
        }
    }

    /// Map voxel edge, metres.
    pub fn voxel_m(&self) -> f64 {
        self.voxel_m
    }

    /// Travel per segment, metres.
    pub fn segment_length_m(&self) -> f64 {
        self.segment_length_m
    }

    /// Anchor stamps of the submaps added, in order (index = submap index).
    pub fn submap_stamps(&self) -> &[f64] {
        &self.submap_stamps
    }

    /// Segments so far (the open one included).
    pub fn segment_count(&self) -> usize {
        self.segments.len() + usize::from(self.open.is_some())
    }

    /// Voxels held in memory (all segments): what bounds the map's memory.
    pub fn stored_voxels(&self) -> usize {
        self.segments.iter().map(|s| s.voxels.len()).sum::<usize>()
            + self.open.as_ref().map_or(0, |o| o.rows.len())
    }

    /// Every segment as (reference submap, voxels): the closed ones borrowed, the open one
    /// (only before [`Self::finish`]) closed on a copy.
    fn all_segments(&self) -> Vec<(u32, std::borrow::Cow<'_, [MapVoxel]>)> {
        let mut out: Vec<(u32, std::borrow::Cow<'_, [MapVoxel]>)> = self
            .segments
            .iter()
            .map(|s| (s.reference, std::borrow::Cow::Borrowed(s.voxels.as_slice())))
            .collect();
        if let Some(open) = &self.open {
            let copy = OpenSegment {
                reference: open.reference,
                reference_from_world: open.reference_from_world,
                travelled_m: open.travelled_m,
                last_position: open.last_position,
                rows: open.rows.clone(),
                merged: open.merged,
            };
            let closed = copy.close();
            out.push((closed.reference, std::borrow::Cow::Owned(closed.voxels)));
        }
        out
    }

    /// Places every voxel by `world_from_submap` (one pose per submap: the trajectory to
    /// render, e.g. the corrected anchor poses, or the odometry for the odometry map) and
    /// merges them into one `voxel_m` grid per pass (`pass_of_submap`, the pass of each
    /// submap; a voxel takes its first submap's pass). Errors name the argument when the
    /// lengths do not match the submaps or `voxel_m` is not positive.
    pub fn render(
        &self,
        world_from_submap: &[Pose],
        pass_of_submap: &[u8],
        voxel_m: f64,
    ) -> Result<MapCloud> {
        let n = self.submap_stamps.len();
        for (name, len) in [
            ("world_from_submap", world_from_submap.len()),
            ("pass_of_submap", pass_of_submap.len()),
        ] {
            if len != n {
                return Err(DecodError::invalid(
                    name,
                    format!("has {len} entries for {n} submaps"),
                ));
            }
        }
        if !(voxel_m.is_finite() && voxel_m > 0.0) {
            return Err(DecodError::invalid(
                "voxel_m",
                format!("must be finite and > 0, got {voxel_m}"),
            ));
        }
        // Correction of each submap: T_world_anchor(k) T_odom_anchor(k)^-1.
        let correction: Vec<Pose> = world_from_submap
            .iter()
            .zip(&self.odom_from_submap)
            .map(|(w, o)| w * o.inverse())
            .collect();
        let inv = 1.0 / voxel_m;
        let odom = &self.odom_from_submap;
        let segments = self.all_segments();
        // Place every voxel (in parallel), then sort by (pass, world voxel) and merge runs:
        // sequential memory access instead of a hash table's random probes.
        let mut placed: Vec<PlacedVoxel> = segments
            .par_iter()
            .flat_map(|(reference, voxels)| {
                let odom_from_reference = odom[*reference as usize];
                let correction = &correction;
                voxels.par_iter().filter_map(move |v| {
                    let k = v.first_submap as usize;
                    let c = v.centroid;
                    let local = Point3::new(f64::from(c[0]), f64::from(c[1]), f64::from(c[2]));
                    let world = correction[k] * (odom_from_reference * local);
                    let key = voxel_key(&world.coords, inv)?;
                    let w = f64::from(v.count);
                    let sum = [w * world.x, w * world.y, w * world.z];
                    Some((
                        placed_key(pass_of_submap[k], key),
                        sum,
                        v.count,
                        v.first_submap,
                    ))
                })
            })
            .collect();
        placed.par_sort_unstable_by_key(|p| p.0);
        Ok(merge_runs(&placed))
    }

    /// Every stored voxel in the anchor frame of the submap that first saw it (odometry
    /// relative pose), with that submap's index; sorted by submap. The clouds per submap of
    /// the 3D recording: together they are the map, each voxel once per segment.
    pub fn points_by_submap(&self) -> (Vec<[f32; 3]>, Vec<u32>) {
        let mut rows: Vec<(u32, [f32; 3])> = Vec::with_capacity(self.stored_voxels());
        let inverse: Vec<Pose> = self.odom_from_submap.iter().map(|p| p.inverse()).collect();
        for (reference, voxels) in self.all_segments() {
            let odom_from_reference = self.odom_from_submap[reference as usize];
            for v in voxels.iter() {
                let k = v.first_submap as usize;
                let c = v.centroid;
                let local = Point3::new(f64::from(c[0]), f64::from(c[1]), f64::from(c[2]));
                let q = inverse[k] * (odom_from_reference * local);
                rows.push((v.first_submap, [q.x as f32, q.y as f32, q.z as f32]));
            }
        }
        rows.sort_by_key(|(k, _)| *k);
        rows.into_iter().map(|(k, p)| (p, k)).unzip()
    }
}

/// The voxel of `p` at `1 / voxel` = `inv`, or None when it is not finite or beyond the
/// i32 range (kilometres at millimetre voxels: never in a corridor, but not a panic).
fn voxel_key(p: &Vector3<f64>, inv: f64) -> Option<[i32; 3]> {
    let limit = f64::from(i32::MAX) - 1.0;
    let mut key = [0i32; 3];
    for (slot, v) in key.iter_mut().zip(p.iter()) {
        let scaled = v * inv;
        if !(scaled.is_finite() && scaled.abs() < limit) {
            return None;
        }
        // floor as a truncation corrected below zero (no libm call on baseline x86-64).
        let t = scaled as i32;
        *slot = if f64::from(t) > scaled { t - 1 } else { t };
    }
    Some(key)
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{Translation3, UnitQuaternion};

    fn pose(x: f64, y: f64, yaw: f64) -> Pose {
        Pose::from_parts(
            Translation3::new(x, y, 0.0),
            UnitQuaternion::from_euler_angles(0.0, 0.0, yaw),
        )
    }

    /// A world point seen from `sensor`: its coordinates in the sensor frame.
    fn seen(sensor: &Pose, world: [f64; 3]) -> [f32; 3] {
        let q = sensor.inverse() * Point3::from(world);
        [q.x as f32, q.y as f32, q.z as f32]
    }

    #[test]
    fn voxels_far_apart_sort_like_their_keys() {
        // Keys spanning the whole i32 range on two axes (a corrupt point far away; one x, so
        // the packed key would need exactly 64 bits): the comparison sort; a narrow range:
        // the radix sort. Both stable, both by (x, y, z).
        for (spread, xs, n) in [(i32::MAX - 2, 1, 40), (300, 3, 400)] {
            let mut rows: Vec<SubmapVoxel> = (0..n)
                .map(|i: i32| SubmapVoxel {
                    key: [
                        (i % xs) * 7,
                        (i * 7919 % 13 - 6) * (spread / 6),
                        (i % 5 - 2) * (spread / 2),
                    ],
                    sum: [f64::from(i), 0.0, 0.0],
                    count: 1,
                    submap: i as u32,
                })
                .collect();
            let mut expected = rows.clone();
            expected.sort_by_key(|r| r.key);
            sort_by_voxel(&mut rows);
            let order = |v: &[SubmapVoxel]| v.iter().map(|r| r.submap).collect::<Vec<_>>();
            assert_eq!(order(&rows), order(&expected));
        }
    }

    #[test]
    fn a_robot_standing_still_adds_no_memory() {
        let mut map = SegmentMap::new(0.05, 1.0).unwrap();
        let sensor = pose(2.0, 0.0, 0.3);
        let wall: Vec<[f32; 3]> = (0..200)
            .map(|i| seen(&sensor, [i as f64 * 0.02, 1.0, 0.5]))
            .collect();
        map.add_submap(0.0, &sensor, &wall);
        let after_one = map.stored_voxels();
        // Enough submaps for the open segment's rows to be merged several times.
        let submaps = 4 * MERGE_MIN_ROWS / after_one;
        let mut most = 0;
        for k in 1..submaps {
            map.add_submap(k as f64, &sensor, &wall);
            most = most.max(map.stored_voxels());
        }
        assert!(most <= MERGE_MIN_ROWS + after_one, "{most} rows held");
        map.finish();
        assert_eq!(map.stored_voxels(), after_one);
        assert_eq!(map.segment_count(), 1);
        assert_eq!(map.submap_stamps().len(), submaps);
    }

    #[test]
    fn memory_grows_with_travel_and_segments_follow_the_schedule() {
        let mut map = SegmentMap::new(0.05, 1.0).unwrap();
        // Anchors every 0.25 m over 10 m: a new segment every 1 m of travel.
        for k in 0..41 {
            let x = k as f64 * 0.25;
            let sensor = pose(x, 0.0, 0.0);
            let wall: Vec<[f32; 3]> = (0..50)
                .map(|i| seen(&sensor, [x + i as f64 * 0.04, 1.0, 0.0]))
                .collect();
            map.add_submap(k as f64, &sensor, &wall);
        }
        map.finish();
        // Travel exceeds 1 m after 5 steps of 0.25 m: 41 anchors make 9 segments.
        assert_eq!(map.segment_count(), 9);
        // The wall spans x in [0, 12) at 0.05 m voxels: 240 distinct voxels, each stored in
        // at most 2 + 1 segments (the reach of 2 m over segments of 1.25 m).
        let stored = map.stored_voxels();
        assert!((240..=720).contains(&stored), "{stored}");
    }

    #[test]
    fn odometry_render_puts_points_where_the_world_has_them() {
        let mut map = SegmentMap::new(0.01, 0.5).unwrap();
        // Off the voxel boundaries (a point on one may round either way).
        let world = [
            [5.003, 1.004, 0.2055],
            [6.005, -1.0045, 0.3035],
            [4.5035, 0.0025, -1.0045],
        ];
        let poses: Vec<Pose> = (0..6).map(|k| pose(k as f64 * 0.3, 0.1, 0.2)).collect();
        for (k, sensor) in poses.iter().enumerate() {
            let pts: Vec<[f32; 3]> = world.iter().map(|w| seen(sensor, *w)).collect();
            map.add_submap(k as f64, sensor, &pts);
        }
        let cloud = map.render(&poses, &[0; 6], 0.01).unwrap();
        assert_eq!(cloud.points.len(), 3);
        assert_eq!(cloud.count.iter().sum::<u32>(), 18);
        for w in world {
            let near = cloud.points.iter().any(|p| {
                (p[0] - w[0]).abs() < 1e-4
                    && (p[1] - w[1]).abs() < 1e-4
                    && (p[2] - w[2]).abs() < 1e-4
            });
            assert!(near, "{w:?} not in {:?}", cloud.points);
        }
    }

    #[test]
    fn each_voxel_moves_with_its_first_submaps_correction() {
        // Submap k sees a distinct point; the corrected trajectory shifts submap k by
        // (0, 0.1 k, 0): the rendered point of submap k moves by exactly that.
        let mut map = SegmentMap::new(0.01, 100.0).unwrap();
        let odom: Vec<Pose> = (0..4)
            .map(|k| pose(k as f64, 0.0, 0.1 * k as f64))
            .collect();
        let world: Vec<[f64; 3]> = (0..4).map(|k| [k as f64 + 0.5, 1.0, 0.0]).collect();
        for (k, (sensor, w)) in odom.iter().zip(&world).enumerate() {
            map.add_submap(k as f64, sensor, &[seen(sensor, *w)]);
        }
        let corrected: Vec<Pose> = odom
            .iter()
            .enumerate()
            .map(|(k, p)| Pose::translation(0.0, 0.1 * k as f64, 0.0) * p)
            .collect();
        let cloud = map.render(&corrected, &[0, 0, 1, 1], 0.01).unwrap();
        assert_eq!(cloud.points.len(), 4);
        for (k, w) in world.iter().enumerate() {
            let i = cloud
                .first_submap
                .iter()
                .position(|&s| s == k as u32)
                .unwrap();
            // Corrected pose = odometry translated by (0, 0.1 k, 0) (rotation unchanged).
            let p = cloud.points[i];
            assert!((p[0] - w[0]).abs() < 1e-5, "{p:?}");
            assert!((p[1] - (w[1] + 0.1 * k as f64)).abs() < 1e-5, "{p:?}");
            assert_eq!(cloud.pass[i], u8::from(k >= 2));
        }
    }

    #[test]
    fn passes_are_kept_apart_and_counts_are_conserved() {
        let mut map = SegmentMap::new(0.05, 0.6).unwrap();
        let mut poses = Vec::new();
        let mut total = 0u32;
        // Out to x = 3 and back over the same wall: every wall voxel once per pass.
        let xs: Vec<f64> = (0..13)
            .map(|k| k as f64 * 0.25)
            .chain((0..12).rev().map(|k| k as f64 * 0.25))
            .collect();
        for (k, x) in xs.iter().enumerate() {
            let sensor = pose(*x, 0.0, 0.0);
            let wall: Vec<[f32; 3]> = (0..25)
                .map(|i| seen(&sensor, [x + i as f64 * 0.04 - 0.5, 1.0, 0.0]))
                .collect();
            total += wall.len() as u32;
            map.add_submap(k as f64, &sensor, &wall);
            poses.push(sensor);
        }
        let pass: Vec<u8> = (0..xs.len()).map(|k| u8::from(k > 12)).collect();
        let cloud = map.render(&poses, &pass, 0.05).unwrap();
        assert_eq!(cloud.count.iter().sum::<u32>(), total);
        let out = cloud.pass.iter().filter(|&&p| p == 0).count();
        let back = cloud.pass.len() - out;
        assert!(out > 50 && back > 50, "{out} {back}");
        // Both passes saw x in [-0.5, 3.46): the same wall, voxel by voxel.
        let keys = |p: u8| -> Vec<i64> {
            let mut v: Vec<i64> = cloud
                .points
                .iter()
                .zip(&cloud.pass)
                .filter(|(_, q)| **q == p)
                .map(|(x, _)| (x[0] / 0.05).floor() as i64)
                .collect();
            v.dedup();
            v
        };
        let (a, b) = (keys(0), keys(1));
        assert!(a.iter().filter(|k| b.contains(k)).count() >= 60);
    }

    #[test]
    fn points_by_submap_partition_the_map_in_anchor_frames() {
        let mut map = SegmentMap::new(0.01, 100.0).unwrap();
        let odom: Vec<Pose> = (0..3).map(|k| pose(k as f64, 0.0, 0.2)).collect();
        for (k, sensor) in odom.iter().enumerate() {
            // Each sees the shared point (10, 0, 0) and its own point.
            let own = seen(sensor, [k as f64 + 0.5, 2.0, 0.0]);
            map.add_submap(k as f64, sensor, &[seen(sensor, [10.0, 0.0, 0.0]), own]);
        }
        let (points, submap) = map.points_by_submap();
        assert_eq!(submap, vec![0, 0, 1, 2]);
        // Submap 1's own point, in its anchor frame.
        let expected = seen(&odom[1], [1.5, 2.0, 0.0]);
        let got = points[2];
        assert!(
            (0..3).all(|i| (got[i] - expected[i]).abs() < 1e-4),
            "{got:?}"
        );
    }

    #[test]
    fn the_run_map_reaches_every_voxel_of_a_dense_wall() {
        // A wall sampled at the submap voxel (5.5 mm) over 1 m x 0.5 m: every map voxel
        // (3 x 5.5 mm) gets points although only every `POINT_STRIDE`-th point is added.
        let mut map = SegmentMap::for_submaps(0.0055, 3.0).unwrap();
        let wall: Vec<[f32; 3]> = (0..180)
            .flat_map(|i| (0..90).map(move |j| [i as f32 * 0.0055, 1.0, j as f32 * 0.0055]))
            .collect();
        map.add_submap(0.0, &Pose::identity(), &wall);
        let cloud = map
            .render(&[Pose::identity()], &[0], map.voxel_m())
            .unwrap();
        let columns = (180.0 * 0.0055 / map.voxel_m()).ceil() as usize;
        let rows = (90.0 * 0.0055 / map.voxel_m()).ceil() as usize;
        assert_eq!(cloud.points.len(), columns * rows);
        assert_eq!(
            cloud.count.iter().sum::<u32>() as usize,
            wall.len() / POINT_STRIDE
        );
    }

    #[test]
    fn bad_arguments_are_named_errors_and_bad_points_are_skipped() {
        assert!(SegmentMap::new(0.0, 1.0).is_err());
        assert!(SegmentMap::new(0.1, f64::NAN).is_err());
        let mut map = SegmentMap::new(0.1, 1.0).unwrap();
        map.add_submap(
            0.0,
            &Pose::identity(),
            &[[f32::NAN, 0.0, 0.0], [1.0, 0.0, 0.0]],
        );
        assert_eq!(map.stored_voxels(), 1);
        let err = map.render(&[], &[0], 0.1).unwrap_err().to_string();
        assert!(err.contains("world_from_submap"), "{err}");
        let err = map
            .render(&[Pose::identity()], &[0], -1.0)
            .unwrap_err()
            .to_string();
        assert!(err.contains("voxel_m"), "{err}");
    }
}
