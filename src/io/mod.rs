//! Native log ingestion (issue 4): ROS 2 (CDR) and ROS 1 messages from MCAP files or rosbag2
//! directories, without a ROS install.
//!
//! - [`log`]: files, channel table, [`inspect`], streaming messages (bounded memory).
//! - [`check`]: read and decode every message (what `decod convert` verifies).
//! - [`cdr`], [`ros1`] and [`wire`]: bounds-checked byte readers for the two encodings.
//! - [`pointcloud`], [`livox`], [`odometry`], [`imu`]: message decoders.
//! - [`tum`]: TUM trajectory files.
//! - [`scans`]: [`ScanStream`], clouds paired with interpolated odometry and IMU.

pub mod cdr;
pub mod check;
pub mod imu;
pub mod livox;
pub mod log;
pub mod messages;
pub mod odometry;
pub mod pointcloud;
pub mod ros1;
pub mod scans;
pub mod tum;
pub mod wire;

#[cfg(test)]
mod fuzz;

pub use check::{TopicCheck, check};
pub use log::{LogSummary, TopicInfo, inspect};
pub use messages::MessageKind;
pub use pointcloud::Cloud;
pub use scans::{OdometrySource, ScanStream, ScanStreamOptions, find_imu_topic};
pub use tum::{read_tum, write_tum};
pub use wire::Encoding;
