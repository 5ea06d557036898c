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

/// Odometry poses sorted by stamp, queried by SE(3) interpolation.
#[derive(Clone, Debug, Default)]
pub struct Trajectory {
    stamps: Vec<f64>,
    poses: Vec<Pose>,
}

impl Trajectory {
    /// Sorts `samples` by stamp; of samples with the same stamp the first is kept.
    pub fn new(mut samples: Vec<(f64, Pose)>) -> Self {
        samples.sort_by(|a, b| a.0.total_cmp(&b.0));
        samples.dedup_by(|b, a| a.0 == b.0);
        let (stamps, poses) = samples.into_iter().unzip();
        Self { stamps, poses }
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
    /// outside `[first, last]` (no extrapolation: odometry gaps at the ends are not guessed).
    pub fn at(&self, stamp: f64) -> Option<Pose> {
        let (first, last) = self.span()?;
        if !(stamp >= first && stamp <= last) {
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

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn interpolates_inside_and_refuses_outside() {
        let a = pose_from_tq([0.0, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0], "a").unwrap();
        let half = std::f64::consts::FRAC_PI_4;
        let b = pose_from_tq([2.0, 0.0, 0.0], [0.0, 0.0, half.sin(), half.cos()], "b").unwrap();
        let traj = Trajectory::new(vec![(11.0, b), (10.0, a)]);
        let mid = traj.at(10.25).unwrap();
        assert!((mid.translation.vector.x - 0.5).abs() < 1e-12);
        assert!((mid.rotation.angle() - std::f64::consts::FRAC_PI_8).abs() < 1e-12);
        assert!(traj.at(11.0).is_some() && traj.at(9.99).is_none() && traj.at(11.01).is_none());
    }
}
