//! Log -> landmarks: the streaming front half of `decod run` (paper Algorithm 1, lines 2–3).
//! Scans stream from the log ([`crate::io::ScanStream`]), accumulate into submaps
//! ([`crate::submap::SubmapBuilder`]) and are extracted a few submaps at a time in parallel
//! ([`crate::extract::extract_all`]). Memory is bounded by `batch` submaps, not by the log;
//! only the scan poses (one per scan), the landmarks and the bounded voxel map of the run
//! ([`crate::map::SegmentMap`], filled beside the extraction) are kept.

use std::path::Path;

use crate::config::DecodConfig;
use crate::error::Result;
use crate::extract::{ExtractionOutcome, extract_all};
use crate::geometry::Pose;
use crate::io::{ScanStream, ScanStreamOptions};
use crate::map::SegmentMap;
use crate::scan::Scan;
use crate::submap::{Submap, SubmapBuilder};
use rayon::prelude::*;

/// What the pose graph needs of a submap once its points are gone.
#[derive(Clone, Debug)]
pub struct SubmapRecord {
    /// Stamp of the anchor scan, seconds.
    pub anchor_stamp: f64,
    /// Odometry pose of the anchor (`T_world_anchor`).
    pub world_from_anchor: Pose,
    /// Stamps of the scans accumulated.
    pub scan_stamps: Vec<f64>,
    /// Points after voxel filtering.
    pub point_count: usize,
    /// The voxel-filtered points in the anchor frame, metres (`Submap::points_in_anchor`).
    pub points_in_anchor: Vec<[f32; 3]>,
}

/// One extracted submap: its record and what extraction found.
pub type ProcessedSubmap = (SubmapRecord, ExtractionOutcome);

/// Streams a log through submaps and extraction, `batch` submaps per step.
pub struct LogProcessor {
    stream: ScanStream,
    builder: SubmapBuilder,
    config: DecodConfig,
    batch: usize,
    pending: Vec<Vec<Scan>>,
    scan_stamps: Vec<f64>,
    scan_poses: Vec<Pose>,
    stream_done: bool,
    map: Option<SegmentMap>,
}

impl LogProcessor {
    /// Opens the log and reads its odometry (see [`ScanStream::open`] for the errors).
    /// `batch` submaps are extracted in parallel per step; 2–4 keeps both cores busy while
    /// bounding memory. The run's voxel map is kept ([`SegmentMap::for_submaps`]; see
    /// [`Self::without_map`]).
    pub fn open(
        path: &Path,
        options: &ScanStreamOptions,
        config: &DecodConfig,
        batch: usize,
    ) -> Result<Self> {
        config.validate()?;
        Ok(Self {
            stream: ScanStream::open(
                path,
                &ScanStreamOptions {
                    gap_periods: config.submap.odometry_gap_periods,
                    ..options.clone()
                },
            )?,
            builder: SubmapBuilder::new(&config.submap),
            config: config.clone(),
            batch: batch.max(1),
            pending: Vec::new(),
            scan_stamps: Vec::new(),
            scan_poses: Vec::new(),
            stream_done: false,
            map: Some(SegmentMap::for_submaps(
                config.submap.voxel_m,
                config.submap.max_range_m,
            )?),
        })
    }

    /// The same processor without the voxel map (saves its memory and ~5 % of the time).
    pub fn without_map(mut self) -> Self {
        self.map = None;
        self
    }

    /// The run's voxel map so far (None when disabled); complete once [`Self::step`] has
    /// returned `None`.
    pub fn map(&self) -> Option<&SegmentMap> {
        self.map.as_ref()
    }

    /// Reads scans until `batch` submaps are complete (or the log ends), extracts them in
    /// parallel and returns them in time order; `None` once everything is processed. Damage
    /// to the log (a cut-off file, a corrupt chunk) and undecodable clouds do not stop it:
    /// they are recorded by the stream ([`Self::stream`]); a file that is not a log is an
    /// error, returned after the submaps completed before it.
    pub fn step(&mut self) -> Result<Option<Vec<ProcessedSubmap>>> {
        while !self.stream_done && self.pending.len() < self.batch {
            match self.stream.next() {
                // An undecodable cloud is counted and named by the stream; only a file that
                // is not a log (the stream then ends) stops the run.
                Some(Err(e)) if self.stream.is_finished() => return Err(e),
                Some(Err(_)) => {}
                Some(Ok(scan)) => {
                    // A submap never spans an odometry gap: the window before it is closed.
                    let crosses = self
                        .scan_stamps
                        .last()
                        .is_some_and(|&previous| self.stream.gap_between(previous, scan.stamp));
                    if crosses {
                        if let Some(window) = self.builder.finish_window() {
                            self.pending.push(window);
                        }
                    }
                    self.scan_stamps.push(scan.stamp);
                    self.scan_poses.push(scan.world_from_body);
                    if let Some(window) = self.builder.push_window(scan)? {
                        self.pending.push(window);
                    }
                }
                None => {
                    self.stream_done = true;
                    if let Some(window) = self.builder.finish_window() {
                        self.pending.push(window);
                    }
                }
            }
        }
        if self.pending.is_empty() {
            if let Some(map) = self.map.as_mut() {
                map.finish();
            }
            return Ok(None);
        }
        // Accumulating a window (0.8-1.5 M points with 64 beams) costs more than extracting
        // its submap: the batch's windows are built in parallel too.
        let windows = std::mem::take(&mut self.pending);
        let submaps = windows
            .par_iter()
            .map(|w| Submap::from_window(w, &self.config.submap))
            .collect::<Result<Vec<_>>>()?;
        drop(windows);
        let config = &self.config;
        let map = &mut self.map;
        // The map is filled on one worker while the others extract.
        let (outcomes, ()) = rayon::join(
            || extract_all(&submaps, config),
            || {
                if let Some(map) = map {
                    for s in &submaps {
                        map.add_submap(s.anchor_stamp, &s.world_from_anchor, &s.points_in_anchor);
                    }
                }
            },
        );
        Ok(Some(
            submaps
                .into_iter()
                .zip(outcomes)
                .map(|(s, o)| {
                    (
                        SubmapRecord {
                            anchor_stamp: s.anchor_stamp,
                            world_from_anchor: s.world_from_anchor,
                            point_count: s.points_in_anchor.len(),
                            scan_stamps: s.scan_stamps,
                            points_in_anchor: s.points_in_anchor,
                        },
                        o,
                    )
                })
                .collect(),
        ))
    }

    /// The scan stream: faults, gaps, skipped and unusable clouds so far.
    pub fn stream(&self) -> &ScanStream {
        &self.stream
    }

    /// Stamps of every scan read so far (odometry-paired), seconds.
    pub fn scan_stamps(&self) -> &[f64] {
        &self.scan_stamps
    }

    /// Odometry pose of every scan read so far, aligned with [`Self::scan_stamps`].
    pub fn scan_poses(&self) -> &[Pose] {
        &self.scan_poses
    }

    /// Scans skipped because they lie outside the odometry span.
    pub fn skipped_outside_odometry(&self) -> &[f64] {
        self.stream.skipped_outside_odometry()
    }

    /// Point-cloud messages in the log (for progress).
    pub fn total_scans_hint(&self) -> u64 {
        self.stream.total_scans_hint()
    }

    /// The point-cloud topic being read.
    pub fn points_topic(&self) -> &str {
        self.stream.points_topic()
    }
}
