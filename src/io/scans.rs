//! The scan stream: point-cloud messages of one topic paired with odometry (a topic or a TUM
//! file) and optionally IMU, yielded one [`Scan`] at a time (DESIGN.md "ingestion").
//!
//! Two passes over the log: the first keeps only the small odometry and IMU messages (and
//! counts every topic; with TUM odometry and no IMU the MCAP summary replaces it), the second streams clouds in file order (= record order, which is
//! log-time order for `ros2 bag record` and rosbags output; clouds are not re-sorted), so
//! memory is bounded by one chunk plus one cloud, not by the log. Measured: reading a 640 MB
//! ROS 1-encoded log (400 clouds of 100k points) from Python peaks at 38 MB RSS against 28 MB
//! for the bare interpreter with numpy and decod_rs imported (688 MB rosbags CDR log: 45 MB),
//! at 42-55 M points/s end to end (both passes, decompression and numpy conversion included).

use std::path::{Path, PathBuf};
use std::sync::Arc;

use super::imu::{ImuSample, ImuSeries};
use super::log::{TopicInfo, log_error, log_files};
use super::messages::{MessageKind, decode_cloud, decode_imu_message, decode_poses};
use super::odometry::{DEFAULT_GAP_PERIODS, OdometryGap, PoseSample, Trajectory};
use super::pointcloud::Cloud;
use super::source::{ChannelMeta, LogFault, MessageSource, PayloadFilter};
use super::tum::read_tum;
use super::wire::Encoding;
use crate::deskew::{MOTION_SPAN_S, Motion, deskew, relative_seconds};
use crate::error::{DecodError, Result};
use crate::geometry::Pose;
use crate::scan::Scan;

/// Where odometry comes from.
#[derive(Clone, Debug, PartialEq)]
pub enum OdometrySource {
    /// A topic of the log (nav_msgs/Odometry, PoseStamped, TransformStamped or TFMessage);
    /// `None` = the unique such topic.
    Topic(Option<String>),
    /// A TUM file (`stamp tx ty tz qx qy qz qw`).
    Tum(PathBuf),
}

/// What to read from a log.
#[derive(Clone, Debug, PartialEq)]
pub struct ScanStreamOptions {
    /// Point-cloud topic (PointCloud2 or Livox CustomMsg); `None` = the unique one.
    pub points_topic: Option<String>,
    /// Odometry source.
    pub odometry: OdometrySource,
    /// IMU topic (sensor_msgs/Imu); `None` = no IMU (see [`find_imu_topic`]).
    pub imu_topic: Option<String>,
    /// IMU samples already read from this log (an earlier stream's [`ScanStream::imu`]):
    /// used instead of reading `imu_topic` again, which takes a pass over the whole file.
    pub imu_samples: Option<Vec<ImuSample>>,
    /// Odometry intervals longer than this many median periods are gaps, not interpolated
    /// (`submap.odometry_gap_periods`; <= 0 turns gap detection off).
    pub gap_periods: f64,
    /// Move each point to the stamp's pose by its own time (`submap.deskew`,
    /// [`crate::deskew`]) where the clouds carry per-point times.
    pub deskew: bool,
}

impl Default for ScanStreamOptions {
    fn default() -> Self {
        Self {
            points_topic: None,
            odometry: OdometrySource::Topic(None),
            imu_topic: None,
            imu_samples: None,
            gap_periods: DEFAULT_GAP_PERIODS,
            deskew: true,
        }
    }
}

/// Messages the stream could not use, per points topic (`report.json` `clouds`).
#[derive(Clone, Debug, Default, PartialEq)]
pub struct CloudStats {
    /// Cloud messages read on the topic.
    pub messages: u64,
    /// Clouds that failed to decode (each yielded an error naming file, topic and time).
    pub undecodable: u64,
    /// Clouds with no point at all (`width * height == 0`).
    pub zero_size: u64,
    /// Clouds whose points were all NaN/inf (empty once those are dropped).
    pub empty: u64,
    /// Points dropped because a coordinate was NaN or infinite.
    pub non_finite_points: u64,
    /// Clouds stamped at or before the previous scan (left out, never reordered).
    pub out_of_order: u64,
    /// Scans whose points were moved to the stamp's pose by their own times
    /// ([`crate::deskew`]).
    pub deskewed: u64,
    /// Scans with a time field whose values are not times within one scan, or without the
    /// trajectory around them: taken as seen from the stamp's pose.
    pub times_unused: u64,
}

/// Most message errors kept per stream (the rest are counted in [`CloudStats`]).
const MAX_MESSAGE_ERRORS: usize = 50;

/// The unique sensor_msgs/Imu topic of the log, `None` if there is none, an error listing
/// them if there are several.
pub fn find_imu_topic(path: &Path) -> Result<Option<String>> {
    let summary = super::log::inspect(path)?;
    let imu = super::log::topics_where(&summary, |t| {
        MessageKind::from_type(t) == Some(MessageKind::Imu)
    });
    match imu.len() {
        0 => Ok(None),
        1 => Ok(imu.into_iter().next()),
        _ => Err(DecodError::Topic {
            path: path.to_path_buf(),
            reason: "several IMU topics; choose one".into(),
            candidates: imu,
        }),
    }
}

/// A channel seen in the first pass.
struct ChannelInfo {
    info: TopicInfo,
    kind: Option<MessageKind>,
}

/// Picks a topic of the wanted kind: the requested one (which must exist and have a
/// suitable type) or the unique candidate.
fn resolve_topic(
    path: &Path,
    channels: &[ChannelInfo],
    requested: Option<&str>,
    what: &str,
    accept: impl Fn(MessageKind) -> bool,
) -> Result<(String, MessageKind, Encoding)> {
    let mut candidates: Vec<String> = channels
        .iter()
        .filter(|c| c.kind.is_some_and(&accept))
        .map(|c| c.info.topic.clone())
        .collect();
    candidates.sort();
    let name = match requested {
        Some(name) => name.to_string(),
        None => match candidates.as_slice() {
            [one] => one.clone(),
            [] => {
                return Err(DecodError::Topic {
                    path: path.to_path_buf(),
                    reason: format!("no {what} topic in the log; all topics listed"),
                    candidates: {
                        let mut all: Vec<String> = channels
                            .iter()
                            .map(|c| format!("{} ({})", c.info.topic, c.info.message_type))
                            .collect();
                        all.sort();
                        all
                    },
                });
            }
            _ => {
                return Err(DecodError::Topic {
                    path: path.to_path_buf(),
                    reason: format!("several {what} topics; choose one"),
                    candidates,
                });
            }
        },
    };
    let Some(channel) = channels.iter().find(|c| c.info.topic == name) else {
        return Err(DecodError::Topic {
            path: path.to_path_buf(),
            reason: format!("no topic `{name}` for {what}"),
            candidates,
        });
    };
    let kind = channel
        .kind
        .filter(|k| accept(*k))
        .ok_or_else(|| DecodError::Unsupported {
            path: path.to_path_buf(),
            topic: name.clone(),
            reason: format!("type `{}` for {what}", channel.info.message_type),
        })?;
    let encoding =
        Encoding::from_mcap(&channel.info.encoding).ok_or_else(|| DecodError::Unsupported {
            path: path.to_path_buf(),
            topic: name.clone(),
            reason: format!(
                "message encoding `{}` (decod reads `cdr` and `ros1`)",
                channel.info.encoding
            ),
        })?;
    Ok((name, kind, encoding))
}

/// Streams [`Scan`]s from a log: see the module doc.
pub struct ScanStream {
    path: PathBuf,
    source: MessageSource,
    points_topic: String,
    points_kind: MessageKind,
    points_encoding: Encoding,
    trajectory: Trajectory,
    imu: Option<ImuSeries>,
    total_scans: u64,
    skipped: Vec<f64>,
    skipped_in_gaps: Vec<f64>,
    out_of_order: Vec<(f64, f64)>,
    stats: CloudStats,
    message_errors: Vec<String>,
    dropped_non_finite: usize,
    previous_stamp: Option<f64>,
    deskew: bool,
    finished: bool,
}

impl ScanStream {
    /// Reads the channel table, odometry and IMU (first pass), resolves the topics and gets
    /// ready to stream clouds. Errors: a missing/ambiguous topic ([`DecodError::Topic`],
    /// with candidates), an unsupported type or encoding ([`DecodError::Unsupported`]), an
    /// undecodable odometry message or empty odometry ([`DecodError::Log`]).
    pub fn open(path: &Path, opts: &ScanStreamOptions) -> Result<Self> {
        let files = log_files(path)?;
        // Pass 1 (skipped when only the channel table is needed and every file has a
        // summary, e.g. odometry from a TUM file without IMU).
        let needs_messages = matches!(opts.odometry, OdometrySource::Topic(_))
            || (opts.imu_topic.is_some() && opts.imu_samples.is_none());
        let summary = if needs_messages {
            None
        } else {
            Some(super::log::inspect(path)?).filter(|s| s.problem.is_none())
        };
        let FirstPass {
            channels,
            kept,
            fault: first_pass_fault,
        } = match summary {
            Some(summary) => FirstPass::from_summary(summary),
            None => FirstPass::read(&files),
        };
        let mut message_errors = Vec::new();
        // A log that fails before its topics are seen: the fault is the error to report.
        let resolved = resolve_topic(
            path,
            &channels,
            opts.points_topic.as_deref(),
            "point cloud (PointCloud2 or Livox CustomMsg)",
            MessageKind::is_points,
        );
        let fault_text = first_pass_fault.as_ref().map(ToString::to_string);
        let (points_topic, points_kind, points_encoding) = match (resolved, first_pass_fault) {
            (Ok(r), _) => r,
            (Err(_), Some(fault)) => return Err(fault),
            (Err(e), None) => return Err(e),
        };
        let total_scans = channels
            .iter()
            .find(|c| c.info.topic == points_topic)
            .map_or(0, |c| c.info.count);

        let trajectory = odometry_trajectory(
            path,
            opts,
            (&channels, &kept),
            &mut message_errors,
            fault_text,
        )?;
        let imu = match (&opts.imu_samples, &opts.imu_topic) {
            (Some(samples), _) => Some(ImuSeries::new(samples.clone())),
            (None, None) => None,
            (None, Some(requested)) => Some(imu_series(path, &channels, &kept, requested)?),
        };
        Ok(Self {
            path: path.to_path_buf(),
            source: MessageSource::new(files),
            points_topic,
            points_kind,
            points_encoding,
            trajectory,
            imu,
            total_scans,
            skipped: Vec::new(),
            skipped_in_gaps: Vec::new(),
            out_of_order: Vec::new(),
            stats: CloudStats::default(),
            message_errors,
            dropped_non_finite: 0,
            previous_stamp: None,
            deskew: opts.deskew,
            finished: false,
        })
    }

    /// Stamps of the clouds skipped so far because they fall outside the odometry span.
    pub fn skipped_outside_odometry(&self) -> &[f64] {
        &self.skipped
    }

    /// Number of cloud messages on the points topic (for progress bars): skipped and faulty
    /// ones included.
    pub fn total_scans_hint(&self) -> u64 {
        self.total_scans
    }

    /// The odometry `(stamp, T_world_body)` series, sorted by stamp.
    pub fn odometry(&self) -> Vec<(f64, Pose)> {
        self.trajectory.samples().map(|(t, p)| (t, *p)).collect()
    }

    /// The IMU samples (sorted by stamp) the stream attaches to its scans; `None` without
    /// an IMU.
    pub fn imu(&self) -> Option<&[ImuSample]> {
        self.imu.as_ref().map(ImuSeries::samples)
    }

    /// The point-cloud topic being read.
    pub fn points_topic(&self) -> &str {
        &self.points_topic
    }

    /// Points dropped so far because a coordinate was NaN or infinite.
    pub fn dropped_non_finite_points(&self) -> usize {
        self.dropped_non_finite
    }

    /// Whether the stream has ended (after `None` or a fatal error).
    pub fn is_finished(&self) -> bool {
        self.finished
    }

    /// Damage met in the log so far (cut-off file, corrupt chunks skipped).
    pub fn faults(&self) -> &[LogFault] {
        self.source.faults()
    }

    /// Odometry intervals not interpolated (gaps, backwards or duplicated stamps).
    pub fn odometry_gaps(&self) -> &[OdometryGap] {
        self.trajectory.gaps()
    }

    /// Whether an odometry gap lies between the scans stamped `t0 < t1` (a submap must not
    /// span it).
    pub fn gap_between(&self, t0: f64, t1: f64) -> bool {
        self.trajectory.gap_between(t0, t1)
    }

    /// Stamps of the clouds left out so far because they fall inside an odometry gap.
    pub fn skipped_in_gaps(&self) -> &[f64] {
        &self.skipped_in_gaps
    }

    /// `(stamp, previous stamp)` of the clouds left out because they were stamped at or
    /// before the previous scan.
    pub fn out_of_order(&self) -> &[(f64, f64)] {
        &self.out_of_order
    }

    /// Counts of unusable clouds and points on the points topic.
    pub fn cloud_stats(&self) -> &CloudStats {
        &self.stats
    }

    /// Messages that failed to decode (odometry and clouds), each naming file, topic and
    /// log time; at most 50 kept.
    pub fn message_errors(&self) -> &[String] {
        &self.message_errors
    }
}

/// What the first pass gathers: the channel table, the raw odometry/IMU messages (small) and
/// the log's fault if it has one. A fault is not fatal here: the second pass meets it again
/// after yielding the scans before it.
struct FirstPass {
    channels: Vec<ChannelInfo>,
    kept: Vec<KeptMessage>,
    fault: Option<DecodError>,
}

/// An odometry or IMU message kept by the first pass.
struct KeptMessage {
    channel: usize,
    file: PathBuf,
    log_time: u64,
    data: Vec<u8>,
}

impl FirstPass {
    /// Reads every message of `files`.
    fn read(files: &[(PathBuf, super::source::Container)]) -> Self {
        let mut channels: Vec<ChannelInfo> = Vec::new();
        let mut kept: Vec<KeptMessage> = Vec::new();
        let mut first_pass_fault = None;
        // Only odometry and IMU payloads are kept: the point clouds are read in the second
        // pass, not copied here.
        let kept_kinds: PayloadFilter = Arc::new(|c: &ChannelMeta| {
            MessageKind::from_type(&c.message_type)
                .is_some_and(|k| k.is_odometry() || k == MessageKind::Imu)
        });
        let mut source = MessageSource::new(files.to_vec()).with_payloads(kept_kinds);
        for msg in source.by_ref() {
            let msg = match msg {
                Ok(m) => m,
                Err(e) => {
                    first_pass_fault = Some(e);
                    break;
                }
            };
            let idx = match channels
                .iter()
                .position(|c| c.info.topic == msg.channel.topic)
            {
                Some(i) => i,
                None => {
                    channels.push(ChannelInfo {
                        kind: MessageKind::from_type(&msg.channel.message_type),
                        info: TopicInfo {
                            topic: msg.channel.topic.clone(),
                            message_type: msg.channel.message_type.clone(),
                            encoding: msg.channel.encoding.clone(),
                            count: 0,
                        },
                    });
                    channels.len() - 1
                }
            };
            let channel = &mut channels[idx];
            channel.info.count += 1;
            if channel
                .kind
                .is_some_and(|k| k.is_odometry() || k == MessageKind::Imu)
            {
                let file = files.get(msg.file).map(|f| f.0.clone()).unwrap_or_default();
                kept.push(KeptMessage {
                    channel: idx,
                    file,
                    log_time: msg.log_time,
                    data: msg.data,
                });
            }
        }
        if first_pass_fault.is_none() {
            first_pass_fault = source.faults().first().map(|f| f.to_error(None));
        }
        Self {
            channels,
            kept,
            fault: first_pass_fault,
        }
    }

    /// The channel table from the log's summary, without reading messages.
    fn from_summary(summary: super::log::LogSummary) -> Self {
        let channels = summary
            .topics
            .into_iter()
            .map(|info| ChannelInfo {
                kind: MessageKind::from_type(&info.message_type),
                info,
            })
            .collect();
        Self {
            channels,
            kept: Vec::new(),
            fault: None,
        }
    }
}

/// The odometry trajectory from a TUM file or the odometry topic among the kept messages
/// (`kept` = channel table and messages of the first pass); an error naming the topic and
/// the log's damage (`fault_text`) when it is empty.
fn odometry_trajectory(
    path: &Path,
    opts: &ScanStreamOptions,
    (channels, kept): (&[ChannelInfo], &[KeptMessage]),
    message_errors: &mut Vec<String>,
    fault_text: Option<String>,
) -> Result<Trajectory> {
    let mut odometry_topic = None;
    let trajectory = match &opts.odometry {
        OdometrySource::Tum(tum) => Trajectory::new(read_tum(tum)?, opts.gap_periods),
        OdometrySource::Topic(requested) => {
            let topic = resolve_topic(
                path,
                channels,
                requested.as_deref(),
                "odometry (Odometry, PoseStamped, TransformStamped or TFMessage)",
                MessageKind::is_odometry,
            )?;
            let samples = odometry_samples(&topic, channels, kept, message_errors);
            let chain = single_transform_chain(path, &topic.0, samples)?;
            odometry_topic = Some(topic.0);
            Trajectory::new(chain, opts.gap_periods)
        }
    };
    if trajectory.is_empty() {
        let reason = match fault_text {
            Some(fault) => {
                format!("odometry topic has no messages before the log's damage: {fault}")
            }
            None => "odometry topic has no messages".to_string(),
        };
        return Err(log_error(path, odometry_topic.as_deref(), reason));
    }
    Ok(trajectory)
}

/// The pose samples of the odometry `topic` (name, kind, encoding) among the kept messages,
/// in record order. A message that does not decode is left out and named in `errors` (the
/// interval it leaves becomes a gap if it is long).
fn odometry_samples(
    topic: &(String, MessageKind, Encoding),
    channels: &[ChannelInfo],
    kept: &[KeptMessage],
    errors: &mut Vec<String>,
) -> Vec<PoseSample> {
    let (name, kind, encoding) = topic;
    let mut samples: Vec<PoseSample> = Vec::new();
    for k in kept
        .iter()
        .filter(|k| channels[k.channel].info.topic == *name)
    {
        match decode_poses(*kind, *encoding, &k.data) {
            Ok(decoded) => samples.extend(decoded),
            Err(e) if errors.len() < MAX_MESSAGE_ERRORS => {
                let at = k.log_time as f64 * 1e-9;
                let reason = format!("message at log time {at:.9} s: {e}");
                errors.push(log_error(&k.file, Some(name), reason).to_string());
            }
            Err(_) => {}
        }
    }
    samples
}

/// The IMU series of the `requested` topic among the kept messages.
fn imu_series(
    path: &Path,
    channels: &[ChannelInfo],
    kept: &[KeptMessage],
    requested: &str,
) -> Result<ImuSeries> {
    let (topic, _, encoding) = resolve_topic(
        path,
        channels,
        Some(requested),
        "IMU (sensor_msgs/Imu)",
        |k| k == MessageKind::Imu,
    )?;
    let samples: Vec<ImuSample> = kept
        .iter()
        .filter(|k| channels[k.channel].info.topic == topic)
        .map(|k| {
            decode_imu_message(encoding, &k.data).map_err(|e| log_error(&k.file, Some(&topic), e))
        })
        .collect::<Result<_>>()?;
    Ok(ImuSeries::new(samples))
}

/// A TFMessage topic can carry several frame pairs; odometry must be one chain
/// (`frame_id -> child_frame_id`), so more than one pair is an error listing them.
fn single_transform_chain(
    path: &Path,
    topic: &str,
    samples: Vec<PoseSample>,
) -> Result<Vec<(f64, Pose)>> {
    let mut pairs: Vec<(String, String)> = Vec::new();
    for s in &samples {
        let pair = (s.frame_id.clone(), s.child_frame_id.clone());
        if !pairs.contains(&pair) {
            pairs.push(pair);
        }
    }
    if pairs.len() > 1 {
        return Err(DecodError::Topic {
            path: path.to_path_buf(),
            reason: format!(
                "odometry topic `{topic}` carries several transforms; publish one chain or use a \
                 TUM file"
            ),
            candidates: pairs.iter().map(|(a, b)| format!("{a} -> {b}")).collect(),
        });
    }
    Ok(samples
        .into_iter()
        .map(|s| (s.stamp, s.world_from_body))
        .collect())
}

impl ScanStream {
    /// The next cloud message on the points topic, `None` at the end of the log. Damage to
    /// the log is not an error here: the source records it ([`Self::faults`]) and goes on.
    fn next_cloud_message(&mut self) -> Option<Result<super::source::RawMessage>> {
        loop {
            match self.source.next()? {
                Err(e) => return Some(Err(with_topic(e, &self.points_topic))),
                Ok(m) if m.channel.topic == self.points_topic => return Some(Ok(m)),
                Ok(_) => {}
            }
        }
    }

    /// Records a cloud that failed to decode; the error names file, topic and log time.
    fn undecodable(&mut self, file: &Path, log_time: u64, reason: String) -> DecodError {
        self.stats.undecodable += 1;
        let reason = format!(
            "message at log time {:.9} s: {reason}",
            log_time as f64 * 1e-9
        );
        let err = log_error(file, Some(&self.points_topic), reason);
        if self.message_errors.len() < MAX_MESSAGE_ERRORS {
            self.message_errors.push(err.to_string());
        }
        err
    }

    /// `cloud`'s points moved to the pose at its stamp by their own times, with the motion of
    /// the trajectory over the next [`MOTION_SPAN_S`] (the previous, at its end); counted in
    /// [`CloudStats`] either way.
    fn deskewed(&mut self, cloud: &mut Cloud, at_stamp: &Pose) {
        let stamp = cloud.header.stamp;
        let motion = [MOTION_SPAN_S, -MOTION_SPAN_S].iter().find_map(|&dt| {
            let other = self.trajectory.at(stamp + dt)?;
            Motion::between(at_stamp, &other, dt)
        });
        let times = cloud
            .time_kind
            .and_then(|kind| relative_seconds(&cloud.times, kind, stamp));
        match (motion, times) {
            (Some(motion), Some(times)) => {
                deskew(&mut cloud.points, &times, &motion);
                self.stats.deskewed += 1;
            }
            _ => self.stats.times_unused += 1,
        }
    }

    /// Whether a cloud stamped `stamp` is used: inside the odometry span, outside its gaps,
    /// after the previous scan. Clouds left out are recorded by reason.
    fn usable(&mut self, stamp: f64) -> bool {
        if let Some(previous) = self
            .previous_stamp
            .filter(|&p| p.partial_cmp(&stamp) != Some(std::cmp::Ordering::Less))
        {
            self.stats.out_of_order += 1;
            self.out_of_order.push((stamp, previous));
            return false;
        }
        if self.trajectory.gap_at(stamp).is_some() {
            self.skipped_in_gaps.push(stamp);
            return false;
        }
        true
    }
}

impl Iterator for ScanStream {
    type Item = Result<Scan>;

    /// The next scan. A message that fails to decode yields an error naming the file, topic
    /// and log time, and the stream goes on; damage to the log itself (a cut-off file, a
    /// corrupt chunk) is recorded in [`ScanStream::faults`] and reading goes on as far as the
    /// container allows. Only a file that is not a log ends the stream with an error.
    fn next(&mut self) -> Option<Self::Item> {
        while !self.finished {
            let msg = match self.next_cloud_message() {
                None => {
                    self.finished = true;
                    return None;
                }
                Some(Err(e)) => {
                    self.finished = true;
                    return Some(Err(e));
                }
                Some(Ok(m)) => m,
            };
            self.stats.messages += 1;
            let file = self
                .source
                .files()
                .get(msg.file)
                .map_or_else(|| self.path.clone(), |f| f.0.clone());
            let mut cloud = match decode_cloud(self.points_kind, self.points_encoding, &msg.data) {
                Ok(c) => c,
                Err(e) => return Some(Err(self.undecodable(&file, msg.log_time, e))),
            };
            self.stats.non_finite_points += cloud.dropped_non_finite as u64;
            if cloud.points.is_empty() {
                if cloud.dropped_non_finite == 0 {
                    self.stats.zero_size += 1;
                } else {
                    self.stats.empty += 1;
                }
            }
            let stamp = cloud.header.stamp;
            let inside = self
                .trajectory
                .span()
                .is_some_and(|(a, b)| a <= stamp && stamp <= b);
            if !inside {
                self.skipped.push(stamp);
                continue;
            }
            if !self.usable(stamp) {
                continue;
            }
            let Some(world_from_body) = self.trajectory.at(stamp) else {
                continue; // unreachable: inside the span and outside every gap
            };
            self.dropped_non_finite += cloud.dropped_non_finite;
            if self.deskew && cloud.time_kind.is_some() && !cloud.points.is_empty() {
                self.deskewed(&mut cloud, &world_from_body);
            }
            // IMU window: since the previous cloud (one scan period); the first scan takes
            // the sample nearest to its stamp.
            let t0 = self.previous_stamp.unwrap_or(stamp);
            self.previous_stamp = Some(stamp);
            let specific_force_in_body = self.imu.as_ref().and_then(|imu| imu.mean_over(t0, stamp));
            return Some(Ok(Scan {
                stamp,
                points_in_body: cloud.points,
                world_from_body,
                specific_force_in_body,
            }));
        }
        None
    }
}

/// Adds the points topic to a log-level error.
fn with_topic(err: DecodError, topic: &str) -> DecodError {
    match err {
        DecodError::Log {
            path,
            topic: None,
            reason,
        } => DecodError::Log {
            path,
            topic: Some(topic.to_string()),
            reason,
        },
        other => other,
    }
}
