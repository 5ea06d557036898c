//! A LiDAR scan with its odometry pose: what ingestion produces and submaps consume.

use crate::geometry::Pose;

/// One scan, already paired with odometry (ingestion interpolates the pose at `stamp`).
#[derive(Clone, Debug)]
pub struct Scan {
    /// Scan stamp, seconds.
    pub stamp: f64,
    /// Points in the sensor/body frame at `stamp`, metres (f32: mm precision to 100 km).
    pub points_in_body: Vec<[f32; 3]>,
    /// Odometry pose of the body at `stamp` (`T_world_body`).
    pub world_from_body: Pose,
    /// Mean IMU specific force over the scan in the body frame (m/s^2; points *up* when
    /// static), when an IMU is available. Gravity is its negation.
    pub specific_force_in_body: Option<[f64; 3]>,
}
