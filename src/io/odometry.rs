//! Odometry messages (nav_msgs/Odometry, geometry_msgs/PoseStamped and TransformStamped,
//! tf2_msgs/TFMessage) and the time-indexed trajectory that gives each scan its pose by SE(3)
//! interpolation ([`crate::geometry::interpolate`]; DESIGN.md "ingestion").

use super::wire::{WireReader, WireResult};
use crate::geometry::{Pose, interpolate, pose_from_tq};

/// One odometry sample: header stamp (s), child frame and `T_world_body`.
#[derive(Clone, Debug)]
pub struct PoseSample {
    /// Header stamp, seconds.
    pub stamp: f64,
    /// `header.frame_id` (the world/odometry frame).
    pub frame_id: String,
    /// The body frame (`child_frame_id`; empty for PoseStamped).
    pub child_frame_id: String,
    /// Pose of the body in the world frame.
    pub world_from_body: Pose,
}

fn pose_of(t: [f64; 3], q: [f64; 4]) -> WireResult<Pose> {
    pose_from_tq(t, q, "pose").map_err(|e| e.to_string())
}

/// nav_msgs/Odometry (the twist and covariances are skipped). Its leading fields are laid
/// out like a TransformStamped: header, child_frame_id, then position and orientation.
pub fn decode_odometry<'a, R: WireReader<'a>>(r: &mut R) -> WireResult<PoseSample> {
    decode_transform_stamped(r)
}

/// geometry_msgs/PoseStamped.
pub fn decode_pose_stamped<'a, R: WireReader<'a>>(r: &mut R) -> WireResult<PoseSample> {
    let header = r.header()?;
    let t = r.vec3()?;
    let q = r.quat()?;
    Ok(PoseSample {
        stamp: header.stamp,
        frame_id: header.frame_id,
        child_frame_id: String::new(),
        world_from_body: pose_of(t, q)?,
    })
}

/// geometry_msgs/TransformStamped (`T_frame_child`).
pub fn decode_transform_stamped<'a, R: WireReader<'a>>(r: &mut R) -> WireResult<PoseSample> {
    let header = r.header()?;
    let child_frame_id = r.string()?;
    let t = r.vec3()?;
    let q = r.quat()?;
    Ok(PoseSample {
        stamp: header.stamp,
        frame_id: header.frame_id,
        child_frame_id,
        world_from_body: pose_of(t, q)?,
    })
}

/// tf2_msgs/TFMessage: every transform it carries.
pub fn decode_tf_message<'a, R: WireReader<'a>>(r: &mut R) -> WireResult<Vec<PoseSample>> {
    // A TransformStamped takes at least 8 + 4 + 4 + 56 bytes.
    let n = r.seq_len(72)?;
    (0..n).map(|_| decode_transform_stamped(r)).collect()
}

/// Why an odometry interval is not interpolated.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum GapKind {
    /// Consecutive samples further apart than the gap bound (a restarted LIO, a dropout).
    Gap,
    /// A sample stamped earlier than the one before it (in record order).
    Backwards,
    /// A sample stamped the same as the one before it.
    Duplicate,
}

impl GapKind {
    /// `gap`, `backwards` or `duplicate` (the name in `report.json`).
    pub fn name(self) -> &'static str {
        match self {
            Self::Gap => "gap",
            Self::Backwards => "backwards",
            Self::Duplicate => "duplicate",
        }
    }
}

/// An odometry interval `(start, end)` (seconds, both kept samples) inside which no pose is
/// interpolated: scans stamped strictly inside are left out, and no submap spans it.
#[derive(Clone, Debug, PartialEq)]
pub struct OdometryGap {
    /// Stamp of the last sample before the gap, seconds.
    pub start: f64,
    /// Stamp of the first sample after the gap, seconds.
    pub end: f64,
    /// What caused it.
    pub kind: GapKind,
}

/// Default gap bound: an interval longer than this many median odometry periods is a gap
/// (`submap.odometry_gap_periods`).
pub const DEFAULT_GAP_PERIODS: f64 = 5.0;

/// Odometry poses by stamp, in record order with out-of-order samples left out (and their
/// intervals marked as gaps), queried by SE(3) interpolation outside the gaps.
#[derive(Clone, Debug, Default)]
pub struct Trajectory {
    stamps: Vec<f64>,
    poses: Vec<Pose>,
    gaps: Vec<OdometryGap>,
}

impl Trajectory {
    /// Samples in record order, never reordered: a sample stamped at or before the last kept
    /// one is dropped, and the interval it disturbs (from the kept sample at or before it to
    /// the kept sample after the previous one) becomes a [`GapKind::Backwards`] or
    /// [`GapKind::Duplicate`] gap; intervals longer than `gap_periods` times the median
    /// period become [`GapKind::Gap`] gaps (`gap_periods` non-finite or <= 0: none).
    pub fn new(samples: Vec<(f64, Pose)>, gap_periods: f64) -> Self {
        let mut stamps: Vec<f64> = Vec::with_capacity(samples.len());
        let mut poses = Vec::with_capacity(samples.len());
        // (stamp of the dropped sample, index of the last kept sample then, kind)
        let mut anomalies: Vec<(f64, usize, GapKind)> = Vec::new();
        for (t, pose) in samples {
            if !t.is_finite() {
                continue;
            }
            match stamps.last() {
                Some(&last) if t <= last => {
                    let kind = if t == last {
                        GapKind::Duplicate
                    } else {
                        GapKind::Backwards
                    };
                    anomalies.push((t, stamps.len() - 1, kind));
                }
                _ => {
                    stamps.push(t);
                    poses.push(pose);
                }
            }
        }
        let mut gaps: Vec<OdometryGap> = Vec::new();
        for (t, last, kind) in anomalies {
            let first = stamps
                .partition_point(|&s| s <= t)
                .saturating_sub(1)
                .min(last);
            let after = (last + 1).min(stamps.len() - 1);
            gaps.push(OdometryGap {
                start: stamps[first],
                end: stamps[after],
                kind,
            });
        }
        gaps.extend(time_gaps(&stamps, gap_periods));
        gaps.retain(|g| g.end > g.start);
        gaps.sort_by(|a, b| a.start.total_cmp(&b.start));
        Self {
            stamps,
            poses,
            gaps,
        }
    }

    /// The intervals not interpolated, by start.
    pub fn gaps(&self) -> &[OdometryGap] {
        &self.gaps
    }

    /// The gap `stamp` lies strictly inside, if any.
    pub fn gap_at(&self, stamp: f64) -> Option<&OdometryGap> {
        self.gaps.iter().find(|g| g.start < stamp && stamp < g.end)
    }

    /// Whether a gap lies between `t0` and `t1` (`t0 < t1`, both outside gaps).
    pub fn gap_between(&self, t0: f64, t1: f64) -> bool {
        self.gaps.iter().any(|g| t0 < g.end && g.start < t1)
    }

    /// Number of poses.
    pub fn len(&self) -> usize {
        self.stamps.len()
    }

    /// Whether there are no poses.
    pub fn is_empty(&self) -> bool {
        self.stamps.is_empty()
    }

    /// `(first, last)` stamp, `None` when empty.
    pub fn span(&self) -> Option<(f64, f64)> {
        Some((*self.stamps.first()?, *self.stamps.last()?))
    }

    /// The `(stamp, pose)` series.
    pub fn samples(&self) -> impl Iterator<Item = (f64, &Pose)> {
        self.stamps.iter().copied().zip(self.poses.iter())
    }

    /// Pose at `stamp` by SE(3) interpolation between the two bracketing poses; `None`
    /// outside `[first, last]` (no extrapolation: odometry gaps at the ends are not guessed)
    /// and inside a gap ([`Self::gaps`]).
    pub fn at(&self, stamp: f64) -> Option<Pose> {
        let (first, last) = self.span()?;
        if !(stamp >= first && stamp <= last) || self.gap_at(stamp).is_some() {
            return None;
        }
        let i = self.stamps.partition_point(|&s| s <= stamp);
        if i == 0 {
            return self.poses.first().copied();
        }
        let (a, ta) = (&self.poses[i - 1], self.stamps[i - 1]);
        match (self.poses.get(i), self.stamps.get(i)) {
            (Some(b), Some(&tb)) if tb > ta => Some(interpolate(a, b, (stamp - ta) / (tb - ta))),
            _ => Some(*a),
        }
    }
}

/// Intervals of `stamps` (increasing) longer than `periods` times their median interval.
fn time_gaps(stamps: &[f64], periods: f64) -> Vec<OdometryGap> {
    if !(periods.is_finite() && periods > 0.0) || stamps.len() < 3 {
        return Vec::new();
    }
    let mut dt: Vec<f64> = stamps.windows(2).map(|w| w[1] - w[0]).collect();
    let mid = dt.len() / 2;
    let median = *dt.select_nth_unstable_by(mid, f64::total_cmp).1;
    let bound = periods * median;
    stamps
        .windows(2)
        .filter(|w| w[1] - w[0] > bound)
        .map(|w| OdometryGap {
            start: w[0],
            end: w[1],
            kind: GapKind::Gap,
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn interpolates_inside_and_refuses_outside() {
        let a = pose_from_tq([0.0, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0], "a").unwrap();
        let half = std::f64::consts::FRAC_PI_4;
        let b = pose_from_tq([2.0, 0.0, 0.0], [0.0, 0.0, half.sin(), half.cos()], "b").unwrap();
        let traj = Trajectory::new(vec![(10.0, a), (11.0, b)], DEFAULT_GAP_PERIODS);
        let mid = traj.at(10.25).unwrap();
        assert!((mid.translation.vector.x - 0.5).abs() < 1e-12);
        assert!((mid.rotation.angle() - std::f64::consts::FRAC_PI_8).abs() < 1e-12);
        assert!(traj.at(11.0).is_some() && traj.at(9.99).is_none() && traj.at(11.01).is_none());
    }

    fn identity_at(t: f64) -> (f64, Pose) {
        (
            t,
            pose_from_tq([t, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0], "p").unwrap(),
        )
    }

    #[test]
    fn long_intervals_are_gaps_not_interpolated() {
        let mut samples: Vec<_> = (0..20).map(|k| identity_at(f64::from(k) * 0.1)).collect();
        samples.extend((0..20).map(|k| identity_at(5.0 + f64::from(k) * 0.1)));
        let traj = Trajectory::new(samples, DEFAULT_GAP_PERIODS);
        assert_eq!(traj.gaps().len(), 1);
        let gap = &traj.gaps()[0];
        assert_eq!(
            (gap.start, gap.end, gap.kind),
            (1.9000000000000001, 5.0, GapKind::Gap)
        );
        assert!(traj.at(3.0).is_none() && traj.at(1.9).is_some() && traj.at(5.05).is_some());
        assert!(traj.gap_between(1.85, 5.05) && !traj.gap_between(0.1, 1.8));
        // A bound of 0 turns gap detection off.
        assert!(
            Trajectory::new(
                vec![identity_at(0.0), identity_at(0.1), identity_at(9.0)],
                0.0
            )
            .gaps()
            .is_empty()
        );
    }

    #[test]
    fn backwards_and_duplicate_stamps_are_gaps_never_reordered() {
        let stamps = [0.0, 0.1, 0.2, 0.3, 0.25, 0.4, 0.5, 0.5, 0.6, 0.7];
        let traj = Trajectory::new(stamps.iter().map(|&t| identity_at(t)).collect(), 50.0);
        assert_eq!(traj.len(), 8);
        let kinds: Vec<_> = traj
            .gaps()
            .iter()
            .map(|g| (g.start, g.end, g.kind))
            .collect();
        assert_eq!(
            kinds,
            vec![
                (0.2, 0.4, GapKind::Backwards),
                (0.5, 0.6, GapKind::Duplicate)
            ]
        );
        assert!(traj.at(0.3).is_none() && traj.at(0.55).is_none() && traj.at(0.15).is_some());
    }
}
