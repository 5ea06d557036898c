//! Opening a log: a `.mcap` file, a ROS 1 `.bag`, a `.db3` file or a rosbag2 directory (its
//! `.mcap` or `.db3` files, in split order); the container is told by the file's first bytes.
//! Channel table and summary (`decod inspect`) from each container's index when it has one.
//! Messages are streamed by [`super::source::MessageSource`].

use std::fs::File;
use std::io::Read;
use std::path::{Path, PathBuf};

use super::db3::SQLITE_MAGIC;
use super::mcap_file::MCAP_MAGIC;
use super::messages::normalize_type;
use super::source::{ChannelMeta, Container, LogFault, MessageSource};
use crate::error::{DecodError, Result};

/// One topic of a log.
#[derive(Clone, Debug, PartialEq)]
pub struct TopicInfo {
    /// Topic name.
    pub topic: String,
    /// Schema (message type) name as written, e.g. `sensor_msgs/msg/PointCloud2`.
    pub message_type: String,
    /// Message encoding (`cdr`, `ros1`, ...).
    pub encoding: String,
    /// Messages on the topic.
    pub count: u64,
}

/// What a log holds (`decod inspect`).
#[derive(Clone, Debug, PartialEq)]
pub struct LogSummary {
    /// The files read (one, or the splits of a rosbag2 directory).
    pub files: Vec<PathBuf>,
    /// Topics sorted by name.
    pub topics: Vec<TopicInfo>,
    /// Log time of the first message, seconds (`None` when empty).
    pub start: Option<f64>,
    /// Log time of the last message, seconds.
    pub end: Option<f64>,
    /// Why the counts may be partial (a file without summary that is truncated or corrupt).
    pub problem: Option<String>,
    /// The damage met while counting (empty when the counts came from an index).
    pub faults: Vec<LogFault>,
}

impl LogSummary {
    /// Total message count.
    pub fn message_count(&self) -> u64 {
        self.topics.iter().map(|t| t.count).sum()
    }

    /// The topic named `topic`.
    pub fn topic(&self, topic: &str) -> Option<&TopicInfo> {
        self.topics.iter().find(|t| t.topic == topic)
    }
}

/// A [`DecodError::Log`].
pub fn log_error(path: &Path, topic: Option<&str>, reason: impl Into<String>) -> DecodError {
    DecodError::Log {
        path: path.to_path_buf(),
        topic: topic.map(str::to_string),
        reason: reason.into(),
    }
}

fn io_error(path: &Path, source: std::io::Error) -> DecodError {
    DecodError::Io {
        path: path.to_path_buf(),
        source,
    }
}

/// The container of the file `path`, from its first bytes (the extension decides only for
/// files too short or too damaged to tell, so that an empty `.mcap` reads as a cut-off MCAP).
pub fn container_of(path: &Path) -> Result<Container> {
    let mut head = [0u8; 16];
    let n = File::open(path)
        .and_then(|f| f.take(16).read(&mut head))
        .map_err(|e| io_error(path, e))?;
    let head = &head[..n];
    if head.starts_with(MCAP_MAGIC) {
        return Ok(Container::Mcap);
    }
    if head.starts_with(b"#ROSBAG") {
        return Ok(Container::Bag);
    }
    if head.starts_with(SQLITE_MAGIC) {
        return Ok(Container::Db3);
    }
    match path.extension().and_then(|e| e.to_str()) {
        Some("bag") => Ok(Container::Bag),
        Some("db3") => Ok(Container::Db3),
        // The MCAP reader names what is wrong (cut-off magic, bad magic).
        _ => Ok(Container::Mcap),
    }
}

/// `name_0.ext`, `name_1.ext`, ..., `name_10.ext` in split order.
fn sort_splits(files: &mut [PathBuf]) {
    let split_index = |p: &PathBuf| -> (u64, String) {
        let stem = p
            .file_stem()
            .map(|s| s.to_string_lossy().into_owned())
            .unwrap_or_default();
        let idx = stem
            .rsplit('_')
            .next()
            .and_then(|s| s.parse().ok())
            .unwrap_or(0);
        (idx, stem)
    };
    files.sort_by_key(split_index);
}

/// The files of the log `path` with their container: the file itself (`.mcap`, ROS 1
/// `.bag`, `.db3`), or the `.mcap` (else `.db3`) files of a rosbag2 directory in split order.
pub fn log_files(path: &Path) -> Result<Vec<(PathBuf, Container)>> {
    let meta = std::fs::metadata(path).map_err(|e| io_error(path, e))?;
    if meta.is_file() {
        return Ok(vec![(path.to_path_buf(), container_of(path)?)]);
    }
    let entries: Vec<PathBuf> = std::fs::read_dir(path)
        .map_err(|e| io_error(path, e))?
        .filter_map(|entry| entry.ok().map(|e| e.path()))
        .collect();
    for (ext, container) in [("mcap", Container::Mcap), ("db3", Container::Db3)] {
        let mut files: Vec<PathBuf> = entries
            .iter()
            .filter(|p| p.extension().is_some_and(|e| e == ext))
            .cloned()
            .collect();
        if !files.is_empty() {
            sort_splits(&mut files);
            return Ok(files.into_iter().map(|f| (f, container)).collect());
        }
    }
    let hint = if path.join("metadata.yaml").exists() {
        " (a rosbag2 directory whose storage is neither MCAP nor sqlite3)"
    } else {
        ""
    };
    Err(log_error(
        path,
        None,
        format!("no .mcap or .db3 file in directory{hint}"),
    ))
}

fn secs(ns: u64) -> f64 {
    ns as f64 * 1e-9
}

fn summary_of_file(path: &Path) -> Result<Option<mcap::Summary>> {
    let file = File::open(path).map_err(|e| io_error(path, e))?;
    // SAFETY: the map is read-only and only lives in this function; a concurrent truncation
    // of the file by another process is the one way this could fault (same as any mmap user).
    let map = unsafe { memmap2::Mmap::map(&file) }.map_err(|e| io_error(path, e))?;
    Ok(mcap::Summary::read(&map).ok().flatten())
}

/// Adds `count` messages of a channel to `topics`.
fn add_topic(topics: &mut Vec<TopicInfo>, channel: &ChannelMeta, count: u64) {
    match topics.iter_mut().find(|t| t.topic == channel.topic) {
        Some(t) => t.count += count,
        None => topics.push(TopicInfo {
            topic: channel.topic.clone(),
            message_type: channel.message_type.clone(),
            encoding: channel.encoding.clone(),
            count,
        }),
    }
}

/// Topics and time span (ns) of one file.
pub type FileSummary = (Vec<TopicInfo>, Option<u64>, Option<u64>);

/// A file's summary from its container's index, `None` when it has no usable one (a
/// cut-off MCAP, an unclosed bag).
fn indexed_summary(path: &Path, container: Container) -> Result<Option<FileSummary>> {
    match container {
        Container::Db3 => super::db3::db3_summary(path).map(Some),
        Container::Bag => super::bag::bag_summary(path),
        Container::Mcap => {
            let Some(summary) = summary_of_file(path)? else {
                return Ok(None);
            };
            let Some(stats) = summary.stats.as_ref() else {
                return Ok(None);
            };
            let mut topics = Vec::new();
            for channel in summary.channels.values() {
                let meta = ChannelMeta {
                    topic: channel.topic.clone(),
                    message_type: channel
                        .schema
                        .as_ref()
                        .map(|s| s.name.clone())
                        .unwrap_or_default(),
                    encoding: channel.message_encoding.clone(),
                };
                let count = stats
                    .channel_message_counts
                    .get(&channel.id)
                    .copied()
                    .unwrap_or(0);
                add_topic(&mut topics, &meta, count);
            }
            let span = (stats.message_count > 0)
                .then_some((stats.message_start_time, stats.message_end_time));
            Ok(Some((topics, span.map(|s| s.0), span.map(|s| s.1))))
        }
    }
}

/// Topics, types, encodings, counts and time span of a log, from the container's index
/// (MCAP summary, bag index, sqlite3 tables) when every file has one, else by reading the
/// messages (then a truncated or corrupt file gives partial counts, its `faults` and a
/// `problem`, not an error).
pub fn inspect(path: &Path) -> Result<LogSummary> {
    let files = log_files(path)?;
    let mut topics: Vec<TopicInfo> = Vec::new();
    let mut start: Option<u64> = None;
    let mut end: Option<u64> = None;
    let mut faults = Vec::new();
    let mut widen = |t0: u64, t1: u64| {
        start = Some(start.map_or(t0, |v| v.min(t0)));
        end = Some(end.map_or(t1, |v| v.max(t1)));
    };
    for (file, container) in &files {
        if let Some((rows, t0, t1)) = indexed_summary(file, *container)? {
            for row in rows {
                let meta = ChannelMeta {
                    topic: row.topic,
                    message_type: row.message_type,
                    encoding: row.encoding,
                };
                add_topic(&mut topics, &meta, row.count);
            }
            if let (Some(t0), Some(t1)) = (t0, t1) {
                widen(t0, t1);
            }
            continue;
        }
        let mut source = MessageSource::new(vec![(file.clone(), *container)]);
        for msg in source.by_ref() {
            let m = msg?;
            add_topic(&mut topics, &m.channel, 1);
            widen(m.log_time, m.log_time);
        }
        faults.extend_from_slice(source.faults());
    }
    topics.sort_by(|a, b| a.topic.cmp(&b.topic));
    let problem = (!faults.is_empty()).then(|| {
        let all: Vec<String> = faults.iter().map(ToString::to_string).collect();
        all.join("; ")
    });
    Ok(LogSummary {
        files: files.into_iter().map(|(f, _)| f).collect(),
        topics,
        start: start.map(secs),
        end: end.map(secs),
        problem,
        faults,
    })
}

/// Topics of `summary` whose type satisfies `pred` (normalised type names).
pub fn topics_where(summary: &LogSummary, pred: impl Fn(&str) -> bool) -> Vec<String> {
    summary
        .topics
        .iter()
        .filter(|t| pred(&normalize_type(&t.message_type)))
        .map(|t| t.topic.clone())
        .collect()
}
