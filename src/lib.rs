//! decod: DeCOD loop closure for LiDAR SLAM in pipes and tunnels.
//!
//! Pipeline (paper §III): [`submap`] accumulates scans; [`axis`], [`contour`], [`boundary`]
//! and [`descriptor`] turn a submap into [`landmark::Landmark`]s ([`extract`] chains them);
//! [`matching`] associates landmarks across traversals; [`io`] reads MCAP logs; [`map`] keeps
//! the run's bounded voxel map for the corrected point cloud and [`map_quality`] measures how
//! well its passes agree. The pose graph lives in Python (`python/decod_rs/graph.py`);
//! [`landmark_factor`] evaluates its 5-DoF factor.
//! Bindings are in `src/python/`, behind the `python` feature, and nothing else imports pyo3.
#![warn(missing_docs)]

mod accumulate;
pub mod axis;
pub mod boundary;
pub mod centre_line;
pub mod config;
pub mod contour;
pub mod corridor_end;
pub mod descriptor;
pub mod deskew;
pub mod error;
pub mod extract;
pub mod geometry;
pub mod io;
pub mod landmark;
pub mod landmark_factor;
pub mod map;
pub mod map_quality;
pub mod matching;
pub mod park;
pub mod pipeline;
mod radix;
pub mod scan;
pub mod spill;
pub mod submap;
pub mod survey;
pub mod wall_normals;

#[cfg(feature = "python")]
mod python;

pub use config::{DecodConfig, Preset};
pub use error::{DecodError, Result};
pub use landmark::{Descriptor, Landmark};
