//! Log -> landmarks: the streaming front half of `decod run` (paper Algorithm 1, lines 2–3).
//! Scans stream from the log ([`crate::io::ScanStream`]), accumulate into submaps
//! ([`crate::submap::SubmapBuilder`]) and are extracted a few submaps at a time in parallel
//! ([`crate::extract::extract_all`]) while the next few are read: decompressing and decoding
//! the log is one thread's work, which the other cores would otherwise wait for. Memory is
//! bounded by two batches of submaps (the one extracted, the one read), not by the log; only
//! the scan poses (one per scan), the landmarks and the bounded voxel map of the run
//! ([`crate::map::SegmentMap`], filled beside the extraction) are kept.

use std::path::Path;

use crate::config::DecodConfig;
use crate::error::{DecodError, Result};
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
    reader: WindowReader,
    config: DecodConfig,
    /// The batch read while the previous one was extracted, and the error that ended its
    /// reading, if any (`None` before the first step).
    ahead: Option<ReadBatch>,
    map: Option<SegmentMap>,
}

/// Complete windows in time order, and the error that stopped the reading, if any.
type ReadBatch = (Vec<Vec<Scan>>, Option<DecodError>);

/// The reading half of [`LogProcessor`]: scans from the stream, accumulated into windows.
struct WindowReader {
    stream: ScanStream,
    builder: SubmapBuilder,
    batch: usize,
    scan_stamps: Vec<f64>,
    scan_poses: Vec<Pose>,
    done: bool,
}

impl WindowReader {
    /// Reads scans until `batch` windows are complete or the log ends (its last window then
    /// closes). Damage to the log (a cut-off file, a corrupt chunk) and undecodable clouds do
    /// not stop it: the stream records them; a file that is not a log (the stream then ends)
    /// stops it with that error, returned beside the windows completed before it.
    fn read_batch(&mut self) -> ReadBatch {
        let mut windows = Vec::new();
        while !self.done && windows.len() < self.batch {
            match self.stream.next() {
                Some(Err(e)) if self.stream.is_finished() => return (windows, Some(e)),
                Some(Err(_)) => {}
                Some(Ok(scan)) => {
                    // A submap never spans an odometry gap: the window before it is closed.
                    let crosses = self
                        .scan_stamps
                        .last()
                        .is_some_and(|&previous| self.stream.gap_between(previous, scan.stamp));
                    if crosses {
                        windows.extend(self.builder.finish_window());
                    }
                    self.scan_stamps.push(scan.stamp);
                    self.scan_poses.push(scan.world_from_body);
                    match self.builder.push_window(scan) {
                        Ok(window) => windows.extend(window),
                        Err(e) => return (windows, Some(e)),
                    }
                }
                None => {
                    self.done = true;
                    windows.extend(self.builder.finish_window());
                }
            }
        }
        (windows, None)
    }
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
        let stream = ScanStream::open(
            path,
            &ScanStreamOptions {
                gap_periods: config.submap.odometry_gap_periods,
                deskew: config.submap.deskew,
                ..options.clone()
            },
        )?;
        Ok(Self {
            reader: WindowReader {
                stream,
                builder: SubmapBuilder::new(&config.submap),
                batch: batch.max(1),
                scan_stamps: Vec::new(),
                scan_poses: Vec::new(),
                done: false,
            },
            config: config.clone(),
            ahead: None,
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

    /// Extracts the next `batch` submaps in parallel, while the batch after them is read,
    /// and returns them in time order; `None` once everything is processed (the first step
    /// reads its batch alone). Damage to the log (a cut-off file, a corrupt chunk) and
    /// undecodable clouds do not stop it: they are recorded by the stream ([`Self::stream`]);
    /// a file that is not a log is an error, returned after the submaps completed before it
    /// (the next step extracts those).
    pub fn step(&mut self) -> Result<Option<Vec<ProcessedSubmap>>> {
        let (windows, error) = match self.ahead.take() {
            // Nothing complete was read ahead (an error ended that reading): read on.
            Some((windows, error))
                if !windows.is_empty() || error.is_some() || self.reader.done =>
            {
                (windows, error)
            }
            _ => self.reader.read_batch(),
        };
        if let Some(e) = error {
            self.ahead = Some((windows, None));
            return Err(e);
        }
        if windows.is_empty() {
            if let Some(map) = self.map.as_mut() {
                map.finish();
            }
            return Ok(None);
        }
        let reader = &mut self.reader;
        let (config, map) = (&self.config, &mut self.map);
        let (processed, ahead) =
            rayon::join(|| process(windows, config, map), || reader.read_batch());
        self.ahead = Some(ahead);
        processed.map(Some)
    }

    /// The scan stream: faults, gaps, skipped and unusable clouds so far.
    pub fn stream(&self) -> &ScanStream {
        &self.reader.stream
    }

    /// Stamps of every scan read so far (odometry-paired), seconds.
    pub fn scan_stamps(&self) -> &[f64] {
        &self.reader.scan_stamps
    }

    /// Odometry pose of every scan read so far, aligned with [`Self::scan_stamps`].
    pub fn scan_poses(&self) -> &[Pose] {
        &self.reader.scan_poses
    }

    /// Scans skipped because they lie outside the odometry span.
    pub fn skipped_outside_odometry(&self) -> &[f64] {
        self.reader.stream.skipped_outside_odometry()
    }

    /// Point-cloud messages in the log (for progress).
    pub fn total_scans_hint(&self) -> u64 {
        self.reader.stream.total_scans_hint()
    }

    /// Windows `submap.max_travel_m` closed so far ([`SubmapBuilder::closed_by_travel`]).
    pub fn windows_closed_by_travel(&self) -> usize {
        self.reader.builder.closed_by_travel()
    }

    /// The point-cloud topic being read.
    pub fn points_topic(&self) -> &str {
        self.reader.stream.points_topic()
    }
}

/// Builds the submaps of `windows` (in parallel: accumulating a window, 0.8-1.5 M points
/// with 64 beams, costs more than extracting its submap) and extracts them (in parallel),
/// filling the run's voxel map on one worker meanwhile.
fn process(
    windows: Vec<Vec<Scan>>,
    config: &DecodConfig,
    map: &mut Option<SegmentMap>,
) -> Result<Vec<ProcessedSubmap>> {
    let submaps = windows
        .par_iter()
        .map(|w| Submap::from_built_window(w, &config.submap))
        .collect::<Result<Vec<_>>>()?;
    drop(windows);
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
    Ok(submaps
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
        .collect())
}
