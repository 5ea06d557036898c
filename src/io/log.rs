//! Opening a log: a `.mcap` file or a rosbag2 directory (its `.mcap` files, in split order);
//! channel table and summary (`decod inspect`); streaming messages in file order with memory
//! bounded by one chunk (`mcap::io::MessageReader` over a buffered file, chunk CRCs checked).

use std::fs::File;
use std::io::BufReader;
use std::path::{Path, PathBuf};
use std::sync::Arc;

use mcap::sans_io::LinearReaderOptions;

use super::messages::normalize_type;
use crate::error::{DecodError, Result};

/// One topic of a log.
#[derive(Clone, Debug, PartialEq)]
pub struct TopicInfo {
    /// Topic name.
    pub topic: String,
    /// Schema (message type) name as written, e.g. `sensor_msgs/msg/PointCloud2`.
    pub message_type: String,
    /// MCAP message encoding (`cdr`, `ros1`, ...).
    pub encoding: String,
    /// Messages on the topic.
    pub count: u64,
}

/// What a log holds (`decod inspect`).
#[derive(Clone, Debug, PartialEq)]
pub struct LogSummary {
    /// The MCAP files read (one, or the splits of a rosbag2 directory).
    pub files: Vec<PathBuf>,
    /// Topics sorted by name.
    pub topics: Vec<TopicInfo>,
    /// Log time of the first message, seconds (`None` when empty).
    pub start: Option<f64>,
    /// Log time of the last message, seconds.
    pub end: Option<f64>,
    /// Why the counts may be partial (a file without summary that is truncated or corrupt).
    pub problem: Option<String>,
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

/// The MCAP files of `path`: the file itself, or the `.mcap` files of a rosbag2 directory
/// sorted by their split index (`name_0.mcap`, `name_1.mcap`, ..., `name_10.mcap`).
pub fn log_files(path: &Path) -> Result<Vec<PathBuf>> {
    let meta = std::fs::metadata(path).map_err(|e| io_error(path, e))?;
    if meta.is_file() {
        return Ok(vec![path.to_path_buf()]);
    }
    let mut files: Vec<PathBuf> = std::fs::read_dir(path)
        .map_err(|e| io_error(path, e))?
        .filter_map(|entry| entry.ok().map(|e| e.path()))
        .filter(|p| p.extension().is_some_and(|e| e == "mcap"))
        .collect();
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
    if files.is_empty() {
        let hint = if path.join("metadata.yaml").exists() {
            " (a rosbag2 directory with another storage, e.g. sqlite3: re-record or convert \
             with MCAP storage)"
        } else {
            ""
        };
        return Err(log_error(
            path,
            None,
            format!("no .mcap file in directory{hint}"),
        ));
    }
    Ok(files)
}

/// Streams every message of the files in order. Errors (truncation, corrupt chunk, bad
/// record) name the file; after one the stream ends.
pub struct MessageSource {
    files: Vec<PathBuf>,
    next_file: usize,
    current: Option<(PathBuf, mcap::io::MessageReader<BufReader<File>>)>,
    done: bool,
}

/// One message: its channel, log time (ns) and bytes.
pub struct RawMessage {
    /// Channel (topic, schema, encoding).
    pub channel: Arc<mcap::Channel<'static>>,
    /// Log time, nanoseconds.
    pub log_time: u64,
    /// Serialised message.
    pub data: Vec<u8>,
    /// File it came from.
    pub file: usize,
}

/// Chunk or record size above which a file is refused rather than allocated (a corrupt length
/// must not make us allocate gigabytes). 1 GiB is far above any real chunk (MB-sized).
const RECORD_LENGTH_LIMIT: usize = 1 << 30;

impl MessageSource {
    /// A source over `files` (from [`log_files`]).
    pub fn new(files: Vec<PathBuf>) -> Self {
        Self {
            files,
            next_file: 0,
            current: None,
            done: false,
        }
    }

    /// The files read.
    pub fn files(&self) -> &[PathBuf] {
        &self.files
    }
}

impl Iterator for MessageSource {
    type Item = Result<RawMessage>;

    fn next(&mut self) -> Option<Self::Item> {
        while !self.done {
            if self.current.is_none() {
                let path = self.files.get(self.next_file)?.clone();
                self.next_file += 1;
                let file = match File::open(&path) {
                    Ok(f) => f,
                    Err(e) => {
                        self.done = true;
                        return Some(Err(io_error(&path, e)));
                    }
                };
                let options = LinearReaderOptions::default()
                    .with_validate_chunk_crcs(true)
                    .with_record_length_limit(RECORD_LENGTH_LIMIT);
                let reader = mcap::io::MessageReader::new_with_options(
                    BufReader::with_capacity(1 << 20, file),
                    options,
                );
                self.current = Some((path, reader));
            }
            let (path, reader) = self.current.as_mut()?;
            match reader.next() {
                Some(Ok(msg)) => {
                    return Some(Ok(RawMessage {
                        channel: msg.channel,
                        log_time: msg.log_time,
                        data: msg.data.into_owned(),
                        file: self.next_file - 1,
                    }));
                }
                Some(Err(e)) => {
                    self.done = true;
                    let reason = match e {
                        mcap::McapError::BadChunkCrc { .. } => {
                            format!("corrupt chunk (CRC mismatch): {e}")
                        }
                        mcap::McapError::BadMagic => "not an MCAP file (bad magic number); a \
                                                       ROS 1 .bag needs `decod convert` first"
                            .to_string(),
                        mcap::McapError::UnexpectedEof | mcap::McapError::UnexpectedEoc => {
                            format!("truncated file: {e}")
                        }
                        _ => e.to_string(),
                    };
                    return Some(Err(log_error(path, None, reason)));
                }
                None => self.current = None,
            }
        }
        None
    }
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

/// Topics, types, encodings, counts and time span of a log, from the MCAP summary when every
/// file has one, else by reading the messages (then a truncated or corrupt file gives partial
/// counts and a `problem`, not an error).
pub fn inspect(path: &Path) -> Result<LogSummary> {
    let files = log_files(path)?;
    let mut topics: Vec<TopicInfo> = Vec::new();
    let mut start: Option<u64> = None;
    let mut end: Option<u64> = None;
    let mut problem = None;
    let add = |channel: &mcap::Channel<'_>, count: u64, topics: &mut Vec<TopicInfo>| {
        let message_type = channel
            .schema
            .as_ref()
            .map(|s| s.name.clone())
            .unwrap_or_default();
        match topics.iter_mut().find(|t| t.topic == channel.topic) {
            Some(t) => t.count += count,
            None => topics.push(TopicInfo {
                topic: channel.topic.clone(),
                message_type,
                encoding: channel.message_encoding.clone(),
                count,
            }),
        }
    };
    for file in &files {
        match summary_of_file(file)? {
            Some(summary) if summary.stats.is_some() => {
                let stats = summary.stats.as_ref();
                for channel in summary.channels.values() {
                    let count = stats
                        .and_then(|s| s.channel_message_counts.get(&channel.id).copied())
                        .unwrap_or(0);
                    add(channel, count, &mut topics);
                }
                if let Some(s) = stats.filter(|s| s.message_count > 0) {
                    start =
                        Some(start.map_or(s.message_start_time, |v| v.min(s.message_start_time)));
                    end = Some(end.map_or(s.message_end_time, |v| v.max(s.message_end_time)));
                }
            }
            _ => {
                for msg in MessageSource::new(vec![file.clone()]) {
                    match msg {
                        Ok(m) => {
                            add(&m.channel, 1, &mut topics);
                            start = Some(start.map_or(m.log_time, |v| v.min(m.log_time)));
                            end = Some(end.map_or(m.log_time, |v| v.max(m.log_time)));
                        }
                        Err(e) => problem = Some(e.to_string()),
                    }
                }
            }
        }
    }
    topics.sort_by(|a, b| a.topic.cmp(&b.topic));
    Ok(LogSummary {
        files,
        topics,
        start: start.map(secs),
        end: end.map(secs),
        problem,
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
