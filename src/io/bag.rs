//! ROS 1 bags (format 2.0) read natively (issue 11): GEODE and most pipe-robot logs are
//! ROS 1 bags of tens of GB, and a conversion is a full copy.
//!
//! A bag is the line `#ROSBAG V2.0\n` followed by records `header_len: u32, header,
//! data_len: u32, data`; a header is a list of `field_len: u32, name=value` fields, `op`
//! (one byte) saying what the record is: bag header (0x03, `index_pos`), chunk (0x05,
//! `compression` none/bz2/lz4 and uncompressed `size`; its data holds connection (0x07) and
//! message (0x02, `conn`, `time`) records), index data (0x04, after each chunk: `conn`,
//! `count`), and, from `index_pos`, connection and chunk-info (0x06) records.
//!
//! Records are read in file order, one chunk decompressed at a time (memory bounded by a
//! chunk, as for MCAP). Damage is handled as in [`super::mcap_file`]: a cut-off file keeps
//! every complete message; a chunk that does not decompress is skipped and its messages
//! counted from the index records after it. Index records are only used by
//! [`bag_summary`] (`decod inspect`), so a bag that was never closed (no index) streams too.

use std::collections::HashMap;
use std::fs::File;
use std::io::{BufReader, Read, Seek, SeekFrom};
use std::path::{Path, PathBuf};
use std::sync::Arc;

use super::log::{FileSummary, TopicInfo, log_error};
use super::mcap_file::{lz4_frame, read_limited};
use super::source::{
    ChannelMeta, ContainerReader, FaultKind, Item, LogFault, RECORD_LENGTH_LIMIT, RawMessage,
    io_error, le_u32, le_u64,
};
use crate::error::Result;

/// The first line of a format 2.0 bag.
pub const BAG_MAGIC: &[u8; 13] = b"#ROSBAG V2.0\n";

/// Record opcodes (the `op` header field).
mod op {
    pub const MESSAGE_DATA: u8 = 0x02;
    pub const BAG_HEADER: u8 = 0x03;
    pub const INDEX_DATA: u8 = 0x04;
    pub const CHUNK: u8 = 0x05;
    pub const CHUNK_INFO: u8 = 0x06;
    pub const CONNECTION: u8 = 0x07;
}

/// One record: its header fields and data.
struct BagRecord {
    offset: u64,
    header: Vec<u8>,
    data: Vec<u8>,
}

/// The `name=value` fields of a record header, or why it is malformed.
/// `(name, value)` pairs of a record header.
type Fields<'a> = Vec<(&'a [u8], &'a [u8])>;

fn fields(header: &[u8]) -> std::result::Result<Fields<'_>, String> {
    let mut out = Vec::new();
    let mut at = 0usize;
    while at < header.len() {
        let len = le_u32(header, at).ok_or("header field length cut off")? as usize;
        let field = header
            .get(at + 4..(at + 4).saturating_add(len))
            .ok_or("header field runs past the header")?;
        let eq = field
            .iter()
            .position(|&b| b == b'=')
            .ok_or("header field without `=`")?;
        out.push((&field[..eq], &field[eq + 1..]));
        at += 4 + len;
    }
    Ok(out)
}

fn field<'a>(fields: &[(&[u8], &'a [u8])], name: &str) -> Option<&'a [u8]> {
    fields
        .iter()
        .find(|(n, _)| *n == name.as_bytes())
        .map(|(_, v)| *v)
}

fn field_u32(fields: &[(&[u8], &[u8])], name: &str) -> std::result::Result<u32, String> {
    field(fields, name)
        .and_then(|v| le_u32(v, 0))
        .ok_or_else(|| format!("record has no 4-byte `{name}` field"))
}

fn field_str(fields: &[(&[u8], &[u8])], name: &str) -> String {
    field(fields, name)
        .map(|v| String::from_utf8_lossy(v).into_owned())
        .unwrap_or_default()
}

/// A ROS time field (`sec: u32, nsec: u32`) in nanoseconds.
fn field_time(fields: &[(&[u8], &[u8])], name: &str) -> std::result::Result<u64, String> {
    let v = field(fields, name).ok_or_else(|| format!("record has no `{name}` field"))?;
    let (sec, nsec) = (le_u32(v, 0), le_u32(v, 4));
    match (sec, nsec) {
        (Some(s), Some(n)) => Ok(u64::from(s) * 1_000_000_000 + u64::from(n)),
        _ => Err(format!("`{name}` is not a 8-byte time")),
    }
}

fn opcode(fields: &[(&[u8], &[u8])]) -> std::result::Result<u8, String> {
    field(fields, "op")
        .and_then(|v| v.first().copied())
        .ok_or_else(|| "record header has no `op` field".to_string())
}

/// The connection of a connection record: topic from its header, type from its data
/// (itself a header: `type`, `md5sum`, `message_definition`, ...).
fn connection(
    fields: &[(&[u8], &[u8])],
    data: &[u8],
) -> std::result::Result<(u32, ChannelMeta), String> {
    let conn = field_u32(fields, "conn")?;
    let inner = self::fields(data)?;
    let meta = ChannelMeta {
        topic: field_str(fields, "topic"),
        message_type: field_str(&inner, "type"),
        encoding: "ros1".into(),
    };
    Ok((conn, meta))
}

/// Reads one record from `reader` at `offset`; `Ok(None)` at a clean end of file; `Err`
/// with the fault kind and reason when the record is cut off or its lengths are absurd.
fn read_record<R: Read>(
    reader: &mut R,
    offset: u64,
    file_len: u64,
) -> std::result::Result<Option<BagRecord>, (FaultKind, String)> {
    if offset == file_len {
        return Ok(None);
    }
    let mut at = offset;
    let mut part = |what: &str| -> std::result::Result<Vec<u8>, (FaultKind, String)> {
        let mut len = [0u8; 4];
        if file_len - at < 4 {
            return Err((
                FaultKind::Truncated,
                format!("file ends inside a record's {what} length"),
            ));
        }
        reader
            .read_exact(&mut len)
            .map_err(|e| (FaultKind::Unreadable, format!("read error: {e}")))?;
        let len = u64::from(u32::from_le_bytes(len));
        if len > RECORD_LENGTH_LIMIT {
            return Err((
                FaultKind::Unreadable,
                format!("record {what} claims {len} bytes"),
            ));
        }
        if len > file_len - at - 4 {
            let reason = format!(
                "record {what} claims {len} bytes but the file ends {} bytes later (cut off, or a corrupt length)",
                file_len - at - 4
            );
            return Err((FaultKind::Truncated, reason));
        }
        let mut buf = vec![0u8; len as usize];
        reader
            .read_exact(&mut buf)
            .map_err(|e| (FaultKind::Unreadable, format!("read error: {e}")))?;
        at += 4 + len;
        Ok(buf)
    };
    let header = part("header")?;
    let data = part("data")?;
    Ok(Some(BagRecord {
        offset,
        header,
        data,
    }))
}

/// Records of a decompressed chunk being read one by one.
struct ChunkCursor {
    data: Vec<u8>,
    at: usize,
    offset: u64,
}

/// A reader of one ROS 1 bag (see the module doc).
pub struct BagFile {
    path: PathBuf,
    reader: BufReader<File>,
    file_len: u64,
    pos: u64,
    index_pos: Option<u64>,
    chunk_count: Option<u32>,
    chunk_infos: u32,
    connections: HashMap<u32, Arc<ChannelMeta>>,
    chunk: Option<ChunkCursor>,
    pending_fault: Option<LogFault>,
    peeked: Option<BagRecord>,
    last_time: Option<u64>,
    done: bool,
}

/// Opens `path` and checks the version line. Errors: unreadable, or not a format 2.0 bag.
fn open_bag(path: &Path) -> Result<(BufReader<File>, u64)> {
    let file = File::open(path).map_err(|e| io_error(path, e))?;
    let file_len = file.metadata().map_err(|e| io_error(path, e))?.len();
    let mut reader = BufReader::with_capacity(1 << 20, file);
    let mut magic = [0u8; 13];
    let n = (&mut reader)
        .take(13)
        .read(&mut magic)
        .map_err(|e| io_error(path, e))?;
    if n < 13 || &magic != BAG_MAGIC {
        let line = String::from_utf8_lossy(&magic[..n]).trim_end().to_string();
        let reason = if line.starts_with("#ROSBAG V") {
            format!("ROS bag version `{line}` is not supported (decod reads format 2.0)")
        } else {
            "not a ROS 1 bag (no `#ROSBAG V2.0` line)".to_string()
        };
        return Err(log_error(path, None, reason));
    }
    Ok((reader, file_len))
}

impl BagFile {
    /// Opens a bag for streaming (see [`open_bag`] for the errors).
    pub fn open(path: &Path) -> Result<Self> {
        let file_len = std::fs::metadata(path)
            .map_err(|e| io_error(path, e))?
            .len();
        if file_len < BAG_MAGIC.len() as u64 {
            return Self::cut_in_magic(path, file_len);
        }
        let (reader, file_len) = open_bag(path)?;
        // A closed bag lists its connections at the end too: with them, a message whose
        // connection record sat in a lost chunk is still readable.
        let connections = read_index(path)?
            .map(|index| index.connections)
            .unwrap_or_default()
            .into_iter()
            .map(|(conn, meta)| (conn, Arc::new(meta)))
            .collect();
        Ok(Self {
            path: path.to_path_buf(),
            reader,
            file_len,
            pos: BAG_MAGIC.len() as u64,
            index_pos: None,
            chunk_count: None,
            chunk_infos: 0,
            connections,
            chunk: None,
            pending_fault: None,
            peeked: None,
            last_time: None,
            done: false,
        })
    }

    /// A bag shorter than its version line: a cut-off file if what is there is the start of
    /// the line, else not a bag.
    fn cut_in_magic(path: &Path, file_len: u64) -> Result<Self> {
        let bytes = std::fs::read(path).map_err(|e| io_error(path, e))?;
        if !BAG_MAGIC.starts_with(&bytes) {
            return Err(log_error(
                path,
                None,
                "not a ROS 1 bag (no `#ROSBAG V2.0` line)",
            ));
        }
        let file = File::open(path).map_err(|e| io_error(path, e))?;
        let mut me = Self {
            path: path.to_path_buf(),
            reader: BufReader::new(file),
            file_len,
            pos: file_len,
            index_pos: None,
            chunk_count: None,
            chunk_infos: 0,
            connections: HashMap::new(),
            chunk: None,
            pending_fault: None,
            peeked: None,
            last_time: None,
            done: true,
        };
        me.pending_fault = Some(me.fault(
            FaultKind::Truncated,
            0,
            "file ends inside the bag's version line",
        ));
        Ok(me)
    }

    fn fault(&self, kind: FaultKind, offset: u64, reason: impl Into<String>) -> LogFault {
        LogFault::new(&self.path, kind, offset, reason, self.last_time)
    }

    /// Connection and message records (top level or in a chunk); a message is returned.
    fn handle(
        &mut self,
        header: &[u8],
        data: &[u8],
        offset: u64,
    ) -> std::result::Result<Option<RawMessage>, LogFault> {
        let corrupt = |me: &Self, e: String| {
            me.fault(
                FaultKind::Corrupt,
                offset,
                format!("malformed record skipped: {e}"),
            )
        };
        let f = fields(header).map_err(|e| corrupt(self, e))?;
        match opcode(&f).map_err(|e| corrupt(self, e))? {
            op::CONNECTION => {
                let (conn, meta) = connection(&f, data).map_err(|e| corrupt(self, e))?;
                self.connections.insert(conn, Arc::new(meta));
            }
            op::MESSAGE_DATA => {
                let conn = field_u32(&f, "conn").map_err(|e| corrupt(self, e))?;
                let time = field_time(&f, "time").map_err(|e| corrupt(self, e))?;
                let Some(channel) = self.connections.get(&conn) else {
                    return Err(corrupt(
                        self,
                        format!("message on unknown connection {conn}"),
                    ));
                };
                self.last_time = Some(time);
                return Ok(Some(RawMessage {
                    channel: channel.clone(),
                    log_time: time,
                    data: data.to_vec(),
                    file: 0,
                }));
            }
            op::BAG_HEADER => {
                self.index_pos = field(&f, "index_pos").and_then(|v| le_u64(v, 0));
                self.chunk_count = field(&f, "chunk_count").and_then(|v| le_u32(v, 0));
            }
            _ => {}
        }
        Ok(None)
    }

    fn next_in_chunk(&mut self) -> Option<std::result::Result<Option<RawMessage>, LogFault>> {
        let cursor = self.chunk.as_mut()?;
        let offset = cursor.offset;
        if cursor.at >= cursor.data.len() {
            self.chunk = None;
            return None;
        }
        let len = cursor.data.len() as u64;
        let mut slice = cursor.data.get(cursor.at..).unwrap_or_default();
        match read_record(&mut slice, cursor.at as u64, len) {
            Ok(Some(r)) => {
                cursor.at = len as usize - slice.len();
                Some(self.handle(&r.header, &r.data, offset))
            }
            Ok(None) => None,
            Err((_, reason)) => {
                self.chunk = None;
                let reason = format!("chunk content: {reason}; rest of the chunk skipped");
                Some(Err(self.fault(FaultKind::Corrupt, offset, reason)))
            }
        }
    }

    fn open_chunk(&mut self, record: &BagRecord) {
        let result = fields(&record.header).and_then(|f| {
            let size = field_u32(&f, "size")? as usize;
            let compression = field_str(&f, "compression");
            decompress(&compression, &record.data, size)
        });
        match result {
            Ok(data) => {
                self.chunk = Some(ChunkCursor {
                    data,
                    at: 0,
                    offset: record.offset,
                })
            }
            Err(reason) => {
                let mut fault = self.fault(
                    FaultKind::Corrupt,
                    record.offset,
                    format!("chunk skipped: {reason}"),
                );
                fault.messages_lost = Some(0);
                self.pending_fault = Some(fault);
            }
        }
    }

    /// The next top-level record, or the fault that ends the file.
    fn next_record(&mut self) -> std::result::Result<Option<BagRecord>, LogFault> {
        if let Some(r) = self.peeked.take() {
            return Ok(Some(r));
        }
        match read_record(&mut self.reader, self.pos, self.file_len) {
            Ok(Some(r)) => {
                self.pos += 8 + r.header.len() as u64 + r.data.len() as u64;
                Ok(Some(r))
            }
            Ok(None) if self.index_pos.is_none_or(|p| p == 0 || p > self.file_len) => {
                let reason =
                    "the bag has no index (recording not closed, or cut off at a record boundary)";
                Err(self.fault(FaultKind::Truncated, self.pos, reason))
            }
            Ok(None) if self.chunk_count.is_some_and(|n| self.chunk_infos < n) => {
                let reason = format!(
                    "file ends inside the index section ({} of {} chunk-info records)",
                    self.chunk_infos,
                    self.chunk_count.unwrap_or(0)
                );
                let mut fault = self.fault(FaultKind::Truncated, self.pos, reason);
                fault.messages_lost = Some(0);
                Err(fault)
            }
            Ok(None) => Ok(None),
            Err((kind, reason)) => Err(self.fault(kind, self.pos, reason)),
        }
    }

    fn next_record_item(&mut self) -> Option<Item> {
        loop {
            if let Some(step) = self.next_in_chunk() {
                match step {
                    Ok(Some(msg)) => return Some(Item::Message(msg)),
                    Ok(None) => continue,
                    Err(fault) => return Some(Item::Fault(fault)),
                }
            }
            let record = match self.next_record() {
                Ok(Some(r)) => r,
                Ok(None) => {
                    self.done = true;
                    return self.pending_fault.take().map(Item::Fault);
                }
                Err(fault) => {
                    self.done = true;
                    let first = self.pending_fault.replace(fault);
                    return first.or_else(|| self.pending_fault.take()).map(Item::Fault);
                }
            };
            let f = fields(&record.header).unwrap_or_default();
            let opcode = opcode(&f).unwrap_or(0);
            if let Some(mut fault) = self.pending_fault.take() {
                if opcode == op::INDEX_DATA {
                    let count = field_u32(&f, "count").unwrap_or(0);
                    fault.messages_lost = Some(fault.messages_lost.unwrap_or(0) + u64::from(count));
                    self.pending_fault = Some(fault);
                    continue;
                }
                self.peeked = Some(record);
                return Some(Item::Fault(fault));
            }
            match opcode {
                op::CHUNK => self.open_chunk(&record),
                op::CHUNK_INFO => self.chunk_infos += 1,
                op::INDEX_DATA => {}
                _ => match self.handle(&record.header, &record.data, record.offset) {
                    Ok(Some(msg)) => return Some(Item::Message(msg)),
                    Ok(None) => {}
                    Err(fault) => return Some(Item::Fault(fault)),
                },
            }
        }
    }
}

impl ContainerReader for BagFile {
    fn next_item(&mut self) -> Option<Item> {
        if self.done {
            return self.pending_fault.take().map(Item::Fault);
        }
        self.next_record_item()
    }
}

/// A chunk's data decompressed to its declared `size` (none, bz2 or lz4 frames).
fn decompress(compression: &str, data: &[u8], size: usize) -> std::result::Result<Vec<u8>, String> {
    if size as u64 > RECORD_LENGTH_LIMIT {
        return Err(format!("uncompressed size {size} above the limit"));
    }
    let out = match compression {
        "none" => data.to_vec(),
        "lz4" => lz4_frame(data, size)?,
        "bz2" => read_limited(bzip2::read::BzDecoder::new(data), size, "bz2")?,
        other => return Err(format!("unsupported chunk compression `{other}`")),
    };
    if out.len() != size {
        return Err(format!(
            "{compression} chunk decompressed to {} bytes, header says {size}",
            out.len()
        ));
    }
    Ok(out)
}

/// What the index section of a closed bag holds: its connections, message counts per
/// connection and the time span (ns).
struct BagIndex {
    connections: HashMap<u32, ChannelMeta>,
    counts: HashMap<u32, u64>,
    start: Option<u64>,
    end: Option<u64>,
}

/// Reads the index section (connection and chunk-info records at `index_pos`) of a closed
/// bag without reading the chunks; `Ok(None)` when the bag has no usable index.
fn read_index(path: &Path) -> Result<Option<BagIndex>> {
    let (mut reader, file_len) = open_bag(path)?;
    let Ok(Some(head)) = read_record(&mut reader, BAG_MAGIC.len() as u64, file_len) else {
        return Ok(None);
    };
    let Ok(f) = fields(&head.header) else {
        return Ok(None);
    };
    let index_pos = field(&f, "index_pos")
        .and_then(|v| le_u64(v, 0))
        .unwrap_or(0);
    if opcode(&f) != Ok(op::BAG_HEADER) || index_pos == 0 || index_pos >= file_len {
        return Ok(None);
    }
    reader
        .seek(SeekFrom::Start(index_pos))
        .map_err(|e| io_error(path, e))?;
    let mut index = BagIndex {
        connections: HashMap::new(),
        counts: HashMap::new(),
        start: None,
        end: None,
    };
    let mut pos = index_pos;
    while let Ok(Some(record)) = read_record(&mut reader, pos, file_len) {
        pos += 8 + record.header.len() as u64 + record.data.len() as u64;
        let Ok(f) = fields(&record.header) else {
            return Ok(None);
        };
        match opcode(&f) {
            Ok(op::CONNECTION) => {
                let Ok((conn, meta)) = connection(&f, &record.data) else {
                    return Ok(None);
                };
                index.connections.insert(conn, meta);
            }
            Ok(op::CHUNK_INFO) => {
                let (Ok(t0), Ok(t1)) = (field_time(&f, "start_time"), field_time(&f, "end_time"))
                else {
                    return Ok(None);
                };
                index.start = Some(index.start.map_or(t0, |s| s.min(t0)));
                index.end = Some(index.end.map_or(t1, |e| e.max(t1)));
                for pair in record.data.chunks_exact(8) {
                    let (conn, count) =
                        (le_u32(pair, 0).unwrap_or(0), le_u32(pair, 4).unwrap_or(0));
                    *index.counts.entry(conn).or_default() += u64::from(count);
                }
            }
            _ => {}
        }
    }
    Ok(Some(index))
}

/// Topics, counts and time span of a closed bag from its index; `Ok(None)` when the bag
/// has no usable index (then the caller reads the messages).
pub fn bag_summary(path: &Path) -> Result<Option<FileSummary>> {
    let Some(index) = read_index(path)? else {
        return Ok(None);
    };
    let rows = index.connections.iter().map(|(conn, meta)| TopicInfo {
        topic: meta.topic.clone(),
        message_type: meta.message_type.clone(),
        encoding: meta.encoding.clone(),
        count: index.counts.get(conn).copied().unwrap_or(0),
    });
    Ok(Some((merge_topics(rows), index.start, index.end)))
}

/// Connections of the same topic (several publishers) merged into one row.
fn merge_topics(rows: impl Iterator<Item = TopicInfo>) -> Vec<TopicInfo> {
    let mut out: Vec<TopicInfo> = Vec::new();
    for row in rows {
        match out.iter_mut().find(|t| t.topic == row.topic) {
            Some(t) => t.count += row.count,
            None => out.push(row),
        }
    }
    out
}
