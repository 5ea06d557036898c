//! Messages from any of the three containers (issue 11): MCAP ([`super::mcap_file`]), ROS 1
//! bags ([`super::bag`]) and ROS 2 sqlite3 bags ([`super::db3`]), streamed in file order by
//! one [`MessageSource`].
//!
//! A damaged log is read as far as it can be: each container reader turns what it cannot
//! read into a [`LogFault`] (a cut-off file, a corrupt chunk skipped) and goes on where the
//! format allows it, so every complete message before a cut is used and a bad chunk in the
//! middle costs only its own time span. Only a file that is not a log at all (wrong magic,
//! unreadable) is an error.

use std::fmt;
use std::path::{Path, PathBuf};
use std::sync::Arc;

use crate::error::{DecodError, Result};

/// Which channels' message payloads a reader returns (see [`MessageSource::with_payloads`]).
pub type PayloadFilter = Arc<dyn Fn(&ChannelMeta) -> bool + Send + Sync>;

/// One channel (topic) of a log, whatever the container.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct ChannelMeta {
    /// Topic name.
    pub topic: String,
    /// Message type as written (`sensor_msgs/msg/PointCloud2`, `sensor_msgs/PointCloud2`).
    pub message_type: String,
    /// Message encoding (`cdr`, `ros1`).
    pub encoding: String,
}

/// One message: its channel, log (receive) time and bytes.
#[derive(Clone, Debug)]
pub struct RawMessage {
    /// Channel (topic, type, encoding).
    pub channel: Arc<ChannelMeta>,
    /// Log time, nanoseconds.
    pub log_time: u64,
    /// Serialised message.
    pub data: Vec<u8>,
    /// Index of the file it came from (in [`MessageSource::files`]).
    pub file: usize,
}

/// What kind of damage a [`LogFault`] is.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum FaultKind {
    /// The file ends in the middle of a record (a recording cut off): reading of the file
    /// stopped there; every complete message before was read.
    Truncated,
    /// A chunk or record was corrupt (CRC mismatch, undecompressible, malformed) and was
    /// skipped; reading went on after it.
    Corrupt,
    /// The file's structure could not be followed past this point (e.g. an unreadable
    /// database page): reading of the file stopped.
    Unreadable,
}

impl FaultKind {
    /// `truncated`, `corrupt` or `unreadable` (the name in `report.json`).
    pub fn name(self) -> &'static str {
        match self {
            Self::Truncated => "truncated",
            Self::Corrupt => "corrupt",
            Self::Unreadable => "unreadable",
        }
    }
}

/// Damage found while reading a log, and what it cost.
#[derive(Clone, Debug, PartialEq)]
pub struct LogFault {
    /// The file at fault.
    pub file: PathBuf,
    /// What happened.
    pub kind: FaultKind,
    /// Byte offset of the record at fault (for sqlite3: the message row id).
    pub offset: u64,
    /// Why, in words.
    pub reason: String,
    /// Log time of the last complete message read before the fault, nanoseconds.
    pub last_complete_ns: Option<u64>,
    /// Log-time span of the messages lost, nanoseconds, when the container says.
    pub lost_span_ns: Option<(u64, u64)>,
    /// Messages lost, when the container says (an index, the summary).
    pub messages_lost: Option<u64>,
}

impl LogFault {
    /// A fault in `file` at `offset`, after the last complete message at `last_complete_ns`;
    /// what it cost (span, messages) unknown until the caller says.
    pub fn new(
        file: &Path,
        kind: FaultKind,
        offset: u64,
        reason: impl Into<String>,
        last_complete_ns: Option<u64>,
    ) -> Self {
        Self {
            file: file.to_path_buf(),
            kind,
            offset,
            reason: reason.into(),
            last_complete_ns,
            lost_span_ns: None,
            messages_lost: None,
        }
    }

    /// What happened and what it cost, without the file name.
    pub fn describe(&self) -> String {
        let secs = |ns: u64| ns as f64 * 1e-9;
        let mut out = format!(
            "{} at byte {}: {}",
            self.kind.name(),
            self.offset,
            self.reason
        );
        match self.last_complete_ns {
            Some(t) => out += &format!("; last complete message at log time {:.9} s", secs(t)),
            None => out += "; no complete message before it",
        }
        if let Some((a, b)) = self.lost_span_ns {
            out += &format!("; log time {:.9}..{:.9} s lost", secs(a), secs(b));
        }
        if let Some(n) = self.messages_lost {
            out += &format!("; {n} messages lost");
        }
        out
    }

    /// The fault as a [`DecodError::Log`] naming the file (and `topic` when given).
    pub fn to_error(&self, topic: Option<&str>) -> DecodError {
        super::log::log_error(&self.file, topic, self.describe())
    }
}

impl fmt::Display for LogFault {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{}: {}", self.file.display(), self.describe())
    }
}

/// What a container reader yields.
pub(crate) enum Item {
    /// A complete message (its `file` field is set by [`MessageSource`]).
    Message(RawMessage),
    /// Damage; the reader goes on after a [`FaultKind::Corrupt`] and ends after the others.
    Fault(LogFault),
}

/// A reader of one file of one container.
pub(crate) trait ContainerReader: Send {
    /// The next message or fault; `None` at the end of the file (or after a fatal fault).
    fn next_item(&mut self) -> Option<Item>;
}

/// The container of a log file.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Container {
    /// MCAP (a `.mcap` file, or the storage of a rosbag2 directory).
    Mcap,
    /// ROS 1 bag, format 2.0.
    Bag,
    /// rosbag2 sqlite3 storage (`.db3`).
    Db3,
}

/// Faults kept per source; more are counted in [`MessageSource::faults_dropped`] (a file
/// with a damaged message on every record must not grow the report without bound).
pub const MAX_FAULTS_KEPT: usize = 100;

/// Streams every message of the files of a log in order (see the module doc). `Err` items
/// are fatal (a file that is not a log): the stream ends after one.
pub struct MessageSource {
    files: Vec<(PathBuf, Container)>,
    next_file: usize,
    current: Option<Box<dyn ContainerReader>>,
    faults: Vec<LogFault>,
    faults_dropped: usize,
    done: bool,
    payloads: Option<PayloadFilter>,
}

impl MessageSource {
    /// A source over `files` (from [`super::log::log_files`]).
    pub fn new(files: Vec<(PathBuf, Container)>) -> Self {
        Self {
            files,
            next_file: 0,
            current: None,
            faults: Vec::new(),
            faults_dropped: 0,
            done: false,
            payloads: None,
        }
    }

    /// Messages on channels `filter` rejects come with empty data where the container allows
    /// it (MCAP; bag and sqlite3 records are read whole either way). Their count, time and
    /// channel are unchanged.
    pub fn with_payloads(mut self, filter: PayloadFilter) -> Self {
        self.payloads = Some(filter);
        self
    }

    /// The files read, with their container.
    pub fn files(&self) -> &[(PathBuf, Container)] {
        &self.files
    }

    /// The faults met so far (at most [`MAX_FAULTS_KEPT`]).
    pub fn faults(&self) -> &[LogFault] {
        &self.faults
    }

    /// Faults met beyond [`MAX_FAULTS_KEPT`] (counted, not kept).
    pub fn faults_dropped(&self) -> usize {
        self.faults_dropped
    }

    fn open(
        path: &Path,
        container: Container,
        payloads: Option<PayloadFilter>,
    ) -> Result<Box<dyn ContainerReader>> {
        Ok(match container {
            Container::Mcap => {
                Box::new(super::mcap_file::McapFile::open(path)?.with_payloads(payloads))
            }
            Container::Bag => Box::new(super::bag::BagFile::open(path)?),
            Container::Db3 => Box::new(super::db3::Db3File::open(path)?),
        })
    }
}

impl Iterator for MessageSource {
    type Item = Result<RawMessage>;

    fn next(&mut self) -> Option<Self::Item> {
        while !self.done {
            if self.current.is_none() {
                let (path, container) = self.files.get(self.next_file)?.clone();
                self.next_file += 1;
                match Self::open(&path, container, self.payloads.clone()) {
                    Ok(reader) => self.current = Some(reader),
                    Err(e) => {
                        self.done = true;
                        return Some(Err(e));
                    }
                }
            }
            let reader = self.current.as_mut()?;
            match reader.next_item() {
                Some(Item::Message(mut msg)) => {
                    msg.file = self.next_file - 1;
                    return Some(Ok(msg));
                }
                Some(Item::Fault(fault)) if self.faults.len() < MAX_FAULTS_KEPT => {
                    self.faults.push(fault);
                }
                Some(Item::Fault(_)) => self.faults_dropped += 1,
                None => self.current = None,
            }
        }
        None
    }
}

/// A [`DecodError::Io`].
pub(crate) fn io_error(path: &Path, source: std::io::Error) -> DecodError {
    DecodError::Io {
        path: path.to_path_buf(),
        source,
    }
}

/// Reads a little-endian `u32` at `at` of `buf`, `None` past the end.
pub(crate) fn le_u32(buf: &[u8], at: usize) -> Option<u32> {
    let b = buf.get(at..at.checked_add(4)?)?;
    Some(u32::from_le_bytes([b[0], b[1], b[2], b[3]]))
}

/// Reads a little-endian `u64` at `at` of `buf`, `None` past the end.
pub(crate) fn le_u64(buf: &[u8], at: usize) -> Option<u64> {
    let b = buf.get(at..at.checked_add(8)?)?;
    let mut a = [0u8; 8];
    a.copy_from_slice(b);
    Some(u64::from_le_bytes(a))
}

/// Record or chunk size above which a file is refused rather than allocated (a corrupt length
/// must not make us allocate gigabytes). 1 GiB is far above any real chunk (MB-sized) or
/// message (a 1M-point cloud is ~30 MB).
pub const RECORD_LENGTH_LIMIT: u64 = 1 << 30;
