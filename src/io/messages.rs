//! Which ROS message types decod reads, and dispatch of raw message bytes to the decoders
//! with the channel's wire encoding.

use super::cdr::CdrReader;
use super::imu::{ImuSample, decode_imu};
use super::livox::decode_custom_msg;
use super::odometry::{
    PoseSample, decode_odometry, decode_pose_stamped, decode_tf_message, decode_transform_stamped,
};
use super::pointcloud::{Cloud, decode_pointcloud2};
use super::ros1::Ros1Reader;
use super::wire::{Encoding, WireResult};

/// A message type decod decodes.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum MessageKind {
    /// sensor_msgs/PointCloud2.
    PointCloud2,
    /// livox_ros_driver/CustomMsg or livox_ros_driver2/CustomMsg.
    LivoxCustom,
    /// nav_msgs/Odometry.
    Odometry,
    /// geometry_msgs/PoseStamped.
    PoseStamped,
    /// geometry_msgs/TransformStamped.
    TransformStamped,
    /// tf2_msgs/TFMessage.
    TfMessage,
    /// sensor_msgs/Imu.
    Imu,
}

/// `pkg/msg/Type` (ROS 2) and `pkg/Type` (ROS 1) both become `pkg/Type`.
pub fn normalize_type(name: &str) -> String {
    name.replacen("/msg/", "/", 1)
}

impl MessageKind {
    /// The kind of a schema name (ROS 1 or ROS 2 spelling), `None` if decod cannot read it.
    pub fn from_type(name: &str) -> Option<Self> {
        Some(match normalize_type(name).as_str() {
            "sensor_msgs/PointCloud2" => Self::PointCloud2,
            "livox_ros_driver/CustomMsg" | "livox_ros_driver2/CustomMsg" => Self::LivoxCustom,
            "nav_msgs/Odometry" => Self::Odometry,
            "geometry_msgs/PoseStamped" => Self::PoseStamped,
            "geometry_msgs/TransformStamped" => Self::TransformStamped,
            "tf2_msgs/TFMessage" => Self::TfMessage,
            "sensor_msgs/Imu" => Self::Imu,
            _ => return None,
        })
    }

    /// A point cloud (PointCloud2 or Livox CustomMsg).
    pub fn is_points(self) -> bool {
        matches!(self, Self::PointCloud2 | Self::LivoxCustom)
    }

    /// A pose source usable as odometry.
    pub fn is_odometry(self) -> bool {
        matches!(
            self,
            Self::Odometry | Self::PoseStamped | Self::TransformStamped | Self::TfMessage
        )
    }
}

/// Runs `f` on a reader of the right encoding over `data`.
macro_rules! with_reader {
    ($encoding:expr, $data:expr, $f:expr) => {
        match $encoding {
            Encoding::Cdr => $f(&mut CdrReader::new($data)?),
            Encoding::Ros1 => $f(&mut Ros1Reader::new($data)),
        }
    };
}

/// Decodes a point-cloud message of `kind` ([`MessageKind::is_points`]).
pub fn decode_cloud(kind: MessageKind, encoding: Encoding, data: &[u8]) -> WireResult<Cloud> {
    match kind {
        MessageKind::PointCloud2 => with_reader!(encoding, data, decode_pointcloud2),
        MessageKind::LivoxCustom => with_reader!(encoding, data, decode_custom_msg),
        other => Err(format!("{other:?} is not a point cloud")),
    }
}

/// Decodes an odometry-like message into its pose samples (several for a TFMessage).
pub fn decode_poses(
    kind: MessageKind,
    encoding: Encoding,
    data: &[u8],
) -> WireResult<Vec<PoseSample>> {
    match kind {
        MessageKind::Odometry => with_reader!(encoding, data, decode_odometry).map(|p| vec![p]),
        MessageKind::PoseStamped => {
            with_reader!(encoding, data, decode_pose_stamped).map(|p| vec![p])
        }
        MessageKind::TransformStamped => {
            with_reader!(encoding, data, decode_transform_stamped).map(|p| vec![p])
        }
        MessageKind::TfMessage => with_reader!(encoding, data, decode_tf_message),
        other => Err(format!("{other:?} is not an odometry message")),
    }
}

/// Decodes a sensor_msgs/Imu.
pub fn decode_imu_message(encoding: Encoding, data: &[u8]) -> WireResult<ImuSample> {
    with_reader!(encoding, data, decode_imu)
}
