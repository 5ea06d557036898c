//! Native log ingestion (issues 4, 11): ROS 2 (CDR) and ROS 1 messages from MCAP files, ROS 1
//! bags, rosbag2 directories (MCAP or sqlite3), without a ROS install; damaged logs read as far
//! as they go, the damage reported ([`LogFault`]).
//!
//! - [`log`]: files and their container, channel table, [`inspect`].
//! - [`source`]: [`source::MessageSource`], messages of any container in file order (bounded
//!   memory), with [`mcap_file`], [`bag`] and [`db3`] the three container readers.
//! - [`check`]: read and decode every message (what `decod convert` verifies).
//! - [`cdr`], [`ros1`] and [`wire`]: bounds-checked byte readers for the two encodings.
//! - [`pointcloud`], [`livox`], [`odometry`], [`imu`]: message decoders.
//! - [`tum`]: TUM trajectory files.
//! - [`scans`]: [`ScanStream`], clouds paired with interpolated odometry and IMU.

pub mod bag;
pub mod cdr;
pub mod check;
pub mod db3;
pub mod imu;
pub mod livox;
pub mod log;
pub mod mcap_file;
pub mod messages;
pub mod odometry;
pub mod pointcloud;
pub mod ros1;
pub mod scans;
pub mod source;
pub mod tum;
pub mod wire;

#[cfg(test)]
mod container_tests;
#[cfg(test)]
mod fuzz;

pub use check::{TopicCheck, check};
pub use log::{LogSummary, TopicInfo, inspect};
pub use messages::MessageKind;
pub use pointcloud::Cloud;
pub use scans::{OdometrySource, ScanStream, ScanStreamOptions, find_imu_topic};
pub use source::{ChannelMeta, Container, FaultKind, LogFault};
pub use tum::{read_tum, write_tum};
pub use wire::Encoding;
