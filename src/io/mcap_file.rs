//! MCAP files read record by record, chunk handling our own (issue 11), so that damage costs
//! only what it touches: a file cut off mid-record yields every complete message before the
//! cut ([`FaultKind::Truncated`] with the byte offset); a chunk whose CRC does not match, or
//! that does not decompress, is skipped with its log-time span and (from the message index
//! records that follow it) its message count ([`FaultKind::Corrupt`]), and reading goes on
//! at the next record. `mcap::MessageReader` stops at the first such error, hence this
//! reader; records are still parsed by `mcap::parse_record`.
//!
//! Memory is bounded by one chunk (compressed and decompressed) plus one message, as before.

use std::collections::HashMap;
use std::fs::File;
use std::io::{BufReader, Read};
use std::path::{Path, PathBuf};
use std::sync::Arc;

use mcap::records::{Record, op};

use super::log::log_error;
use super::source::{
    ChannelMeta, ContainerReader, FaultKind, Item, LogFault, PayloadFilter, RECORD_LENGTH_LIMIT,
    RawMessage, io_error, le_u32, le_u64,
};
use crate::error::Result;

/// The MCAP magic (start and end of a file).
pub const MCAP_MAGIC: &[u8; 8] = b"\x89MCAP0\r\n";

/// Opcode (1) and length (8) bytes before each record body.
const RECORD_PREFIX: u64 = 9;

/// One top-level record: opcode, byte offset and body.
struct RawRecord {
    opcode: u8,
    offset: u64,
    body: Vec<u8>,
}

/// A decompressed chunk being read record by record.
struct ChunkCursor {
    /// The chunk's records from `start` to the end: the decompressed data (`start` 0), or
    /// the record's own body when it is stored uncompressed (no copy).
    data: Vec<u8>,
    start: usize,
    at: usize,
    offset: u64,
}

/// A reader of one MCAP file (see the module doc).
pub struct McapFile {
    path: PathBuf,
    reader: BufReader<File>,
    file_len: u64,
    pos: u64,
    schemas: HashMap<u16, String>,
    channels: HashMap<u16, Arc<ChannelMeta>>,
    chunk: Option<ChunkCursor>,
    pending_fault: Option<LogFault>,
    peeked: Option<RawRecord>,
    /// The largest record buffer done with, reused for the next record body: multi-megabyte
    /// chunks allocated afresh each time cost page faults on every chunk.
    spare: Vec<u8>,
    last_time: Option<u64>,
    in_summary: bool,
    done: bool,
    /// Channels whose message payloads are wanted (all when `None`); the others' messages
    /// come with empty data.
    payloads: Option<PayloadFilter>,
}

impl McapFile {
    /// Messages on channels `filter` rejects come with empty data (a first pass that keeps
    /// odometry and IMU messages need not copy every point cloud).
    pub fn with_payloads(mut self, filter: Option<PayloadFilter>) -> Self {
        self.payloads = filter;
        self
    }

    /// Opens `path` and checks its magic. Errors: the file cannot be opened, or it holds
    /// something else than MCAP. An empty or cut-off magic is a truncation fault instead.
    pub fn open(path: &Path) -> Result<Self> {
        let file = File::open(path).map_err(|e| io_error(path, e))?;
        let file_len = file.metadata().map_err(|e| io_error(path, e))?.len();
        let mut reader = BufReader::with_capacity(1 << 20, file);
        let magic_len = MCAP_MAGIC.len() as u64;
        let cut = file_len < magic_len;
        if !cut {
            let mut magic = [0u8; 8];
            reader
                .read_exact(&mut magic)
                .map_err(|e| io_error(path, e))?;
            if &magic != MCAP_MAGIC {
                return Err(log_error(path, None, "not an MCAP file (bad magic number)"));
            }
        }
        let mut me = Self {
            path: path.to_path_buf(),
            reader,
            file_len,
            pos: if cut { 0 } else { magic_len },
            schemas: HashMap::new(),
            channels: HashMap::new(),
            chunk: None,
            pending_fault: None,
            peeked: None,
            spare: Vec::new(),
            last_time: None,
            in_summary: false,
            done: cut,
            payloads: None,
        };
        if cut {
            let reason = "file ends inside the MCAP magic";
            me.pending_fault = Some(me.fault(FaultKind::Truncated, 0, reason));
        }
        Ok(me)
    }

    fn fault(&self, kind: FaultKind, offset: u64, reason: impl Into<String>) -> LogFault {
        LogFault {
            // Cut inside the summary section: every message was read.
            messages_lost: self.in_summary.then_some(0),
            ..LogFault::new(&self.path, kind, offset, reason, self.last_time)
        }
    }

    /// The next top-level record; `Ok(None)` at a clean end of the file.
    fn read_record(&mut self) -> std::result::Result<Option<RawRecord>, LogFault> {
        if let Some(r) = self.peeked.take() {
            return Ok(Some(r));
        }
        let offset = self.pos;
        let left = self.file_len - offset;
        if left == 0 {
            return Err(self.fault(
                FaultKind::Truncated,
                offset,
                "file ends without a footer (cut off between records)",
            ));
        }
        if left < RECORD_PREFIX {
            return Err(self.fault(
                FaultKind::Truncated,
                offset,
                "file ends inside a record's opcode and length",
            ));
        }
        let mut head = [0u8; 9];
        self.read_exact(&mut head, offset)?;
        let opcode = head[0];
        let len = le_u64(&head, 1).unwrap_or(u64::MAX);
        if len > RECORD_LENGTH_LIMIT {
            let reason = format!(
                "record (opcode {opcode:#04x}) claims {len} bytes, above the {RECORD_LENGTH_LIMIT}-byte limit"
            );
            return Err(self.fault(FaultKind::Unreadable, offset, reason));
        }
        if len > left - RECORD_PREFIX {
            let reason = format!(
                "record (opcode {opcode:#04x}) claims {len} bytes but the file ends {} bytes later (cut off, or a corrupt length)",
                left - RECORD_PREFIX
            );
            return Err(self.fault(FaultKind::Truncated, offset, reason));
        }
        let mut body = std::mem::take(&mut self.spare);
        body.clear();
        body.resize(len as usize, 0);
        self.read_exact(&mut body, offset)?;
        self.pos = offset + RECORD_PREFIX + len;
        Ok(Some(RawRecord {
            opcode,
            offset,
            body,
        }))
    }

    fn read_exact(&mut self, buf: &mut [u8], offset: u64) -> std::result::Result<(), LogFault> {
        self.reader
            .read_exact(buf)
            .map_err(|e| self.fault(FaultKind::Unreadable, offset, format!("read error: {e}")))
    }

    /// Schema and channel records (top level or inside a chunk) fill the channel table; a
    /// message on a known channel is returned.
    fn handle(
        &mut self,
        opcode: u8,
        body: &[u8],
        offset: u64,
    ) -> std::result::Result<Option<RawMessage>, LogFault> {
        if !matches!(opcode, op::SCHEMA | op::CHANNEL | op::MESSAGE) {
            return Ok(None);
        }
        let record = mcap::parse_record(opcode, body).map_err(|e| {
            self.fault(
                FaultKind::Corrupt,
                offset,
                format!("malformed record (opcode {opcode:#04x}) skipped: {e}"),
            )
        })?;
        match record {
            Record::Schema { header, .. } => {
                self.schemas.insert(header.id, header.name);
            }
            Record::Channel(c) => {
                let message_type = self.schemas.get(&c.schema_id).cloned().unwrap_or_default();
                let meta = ChannelMeta {
                    topic: c.topic,
                    message_type,
                    encoding: c.message_encoding,
                };
                self.channels.insert(c.id, Arc::new(meta));
            }
            Record::Message { header, data } => {
                let Some(channel) = self.channels.get(&header.channel_id) else {
                    let reason = format!(
                        "message on unknown channel id {} skipped",
                        header.channel_id
                    );
                    return Err(self.fault(FaultKind::Corrupt, offset, reason));
                };
                self.last_time = Some(header.log_time);
                let wanted = self.payloads.as_ref().is_none_or(|f| f(channel));
                return Ok(Some(RawMessage {
                    channel: channel.clone(),
                    log_time: header.log_time,
                    data: if wanted {
                        data.into_owned()
                    } else {
                        Vec::new()
                    },
                    file: 0,
                }));
            }
            _ => {}
        }
        Ok(None)
    }

    /// The next record of the current chunk, `None` when it is exhausted. The record is
    /// parsed in place (the cursor is taken out of `self` meanwhile): a 64-beam scan is half a
    /// megabyte, copied once into its message, not twice.
    fn next_in_chunk(&mut self) -> Option<std::result::Result<Option<RawMessage>, LogFault>> {
        let mut cursor = self.chunk.take()?;
        let at = cursor.at;
        let offset = cursor.offset;
        if at >= cursor.data.len() {
            self.recycle(cursor.data);
            return None;
        }
        let opcode = cursor.data[at];
        let len = le_u64(&cursor.data, at + 1).and_then(|l| usize::try_from(l).ok());
        let end = len.and_then(|l| (at + RECORD_PREFIX as usize).checked_add(l));
        let Some(end) = end.filter(|&e| e <= cursor.data.len()) else {
            let reason = format!(
                "record at byte {} of the chunk runs past the chunk's end; rest of the chunk skipped",
                at - cursor.start
            );
            return Some(Err(self.fault(FaultKind::Corrupt, offset, reason)));
        };
        let step = self.handle(
            opcode,
            &cursor.data[at + RECORD_PREFIX as usize..end],
            offset,
        );
        cursor.at = end;
        self.chunk = Some(cursor);
        Some(step)
    }

    /// Keeps `buffer` for the next record body if it is larger than the one kept.
    fn recycle(&mut self, buffer: Vec<u8>) {
        if buffer.capacity() > self.spare.capacity() {
            self.spare = buffer;
        }
    }

    /// Decompresses and checks a chunk record; a bad one becomes the pending fault.
    fn open_chunk(&mut self, record: RawRecord) {
        match decompress_chunk(record.body) {
            Ok((data, start)) => {
                self.chunk = Some(ChunkCursor {
                    data,
                    start,
                    at: start,
                    offset: record.offset,
                })
            }
            Err((reason, span)) => {
                let mut fault = self.fault(
                    FaultKind::Corrupt,
                    record.offset,
                    format!("chunk skipped: {reason}"),
                );
                fault.lost_span_ns = span;
                fault.messages_lost = Some(0);
                self.pending_fault = Some(fault);
            }
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
            let record = match self.read_record() {
                Ok(Some(r)) => r,
                Ok(None) => return None,
                Err(fault) => {
                    self.done = true;
                    // A skipped chunk's fault goes out first; the cut follows (`next_item`).
                    let first = self.pending_fault.replace(fault);
                    return first.or_else(|| self.pending_fault.take()).map(Item::Fault);
                }
            };
            if let Some(mut fault) = self.pending_fault.take() {
                if record.opcode == op::MESSAGE_INDEX {
                    // channel id (u16), then the entries' byte length (u32): 8-byte time +
                    // 8-byte offset each.
                    let entries = le_u32(&record.body, 2).map_or(0, |bytes| u64::from(bytes) / 16);
                    fault.messages_lost = Some(fault.messages_lost.unwrap_or(0) + entries);
                    self.pending_fault = Some(fault);
                    self.recycle(record.body);
                    continue;
                }
                self.peeked = Some(record);
                return Some(Item::Fault(fault));
            }
            match record.opcode {
                op::CHUNK => self.open_chunk(record),
                op::DATA_END => self.in_summary = true,
                op::FOOTER => {
                    self.done = true;
                    return self.check_end_magic(record.offset);
                }
                opcode => {
                    let step = self.handle(opcode, &record.body, record.offset);
                    self.recycle(record.body);
                    match step {
                        Ok(Some(msg)) => return Some(Item::Message(msg)),
                        Ok(None) => {}
                        Err(fault) => return Some(Item::Fault(fault)),
                    }
                }
            }
        }
    }

    fn check_end_magic(&mut self, footer_offset: u64) -> Option<Item> {
        let mut magic = [0u8; 8];
        if self.file_len - self.pos < 8 || self.reader.read_exact(&mut magic).is_err() {
            return Some(Item::Fault(self.fault(
                FaultKind::Truncated,
                footer_offset,
                "file ends inside the end magic",
            )));
        }
        None
    }
}

/// Why a chunk is unusable, and its log-time span when its header was readable.
type ChunkError = (String, Option<(u64, u64)>);

/// The chunk's records: `(buffer, start)` with the records in `buffer[start..]`. An
/// uncompressed chunk keeps its record body (`start` past the chunk header), a compressed one
/// is decompressed into a new buffer (`start` 0); both CRC-checked.
fn decompress_chunk(body: Vec<u8>) -> std::result::Result<(Vec<u8>, usize), ChunkError> {
    let (header, data) = match mcap::parse_record(op::CHUNK, &body) {
        Ok(Record::Chunk { header, data }) => (header, data),
        Ok(_) => return Err(("not a chunk".into(), None)),
        Err(e) => return Err((format!("malformed chunk header: {e}"), None)),
    };
    let span = Some((header.message_start_time, header.message_end_time));
    if header.uncompressed_size > RECORD_LENGTH_LIMIT {
        return Err((
            format!(
                "uncompressed size {} above the limit",
                header.uncompressed_size
            ),
            span,
        ));
    }
    let size = header.uncompressed_size as usize;
    // In place, the records follow the chunk header (MCAP: three u64 and a u32, the
    // compression string with its u32 length, the records' u64 length) and run for
    // `data.len()` bytes (anything after them in the record is not the chunk's).
    let in_place = 8 + 8 + 8 + 4 + 4 + header.compression.len() + 8;
    let records_end = in_place + data.len();
    if records_end > body.len() {
        let reason = "malformed chunk header: its records run past the record".to_string();
        return Err((reason, span));
    }
    let decompressed = match header.compression.as_str() {
        "" => None,
        "zstd" => Some(
            zstd::stream::read::Decoder::new(&data[..])
                .map_err(|e| format!("zstd: {e}"))
                .and_then(|d| read_limited(d, size, "zstd")),
        ),
        "lz4" => Some(lz4_frame(&data, size)),
        other => Some(Err(format!("unsupported compression `{other}`"))),
    };
    let crc_stored = header.uncompressed_crc;
    drop(data);
    let (out, start) = match decompressed {
        None => {
            let mut body = body;
            body.truncate(records_end);
            (body, in_place)
        }
        Some(result) => (result.map_err(|e| (e, span))?, 0),
    };
    let records = &out[start..];
    if records.len() != size {
        return Err((
            format!(
                "decompressed to {} bytes, header says {size}",
                records.len()
            ),
            span,
        ));
    }
    if crc_stored != 0 {
        let crc = crc32fast::hash(records);
        if crc != crc_stored {
            let reason = format!("CRC mismatch (stored {crc_stored:#010x}, computed {crc:#010x})");
            return Err((reason, span));
        }
    }
    Ok((out, start))
}

/// Initial capacity of a decompression buffer. A chunk's declared size is not trusted for
/// the allocation (a corrupt header may claim 1 GiB for a few bytes): the buffer grows as the
/// data really decompresses, and stops one byte past the declared size.
const INITIAL_CAPACITY: usize = 1 << 20;

/// Everything `reader` yields up to `size + 1` bytes (so that too long is detectable).
pub(crate) fn read_limited<R: Read>(
    reader: R,
    size: usize,
    what: &str,
) -> std::result::Result<Vec<u8>, String> {
    let mut out = Vec::with_capacity(size.min(INITIAL_CAPACITY));
    reader
        .take(size as u64 + 1)
        .read_to_end(&mut out)
        .map_err(|e| format!("{what}: {e}"))?;
    Ok(out)
}

/// An LZ4 frame decompressed to at most `size` bytes (MCAP and ROS 1 bags both use frames).
pub(crate) fn lz4_frame(data: &[u8], size: usize) -> std::result::Result<Vec<u8>, String> {
    let decoder = lz4::Decoder::new(data).map_err(|e| format!("lz4: {e}"))?;
    read_limited(decoder, size, "lz4")
}

impl ContainerReader for McapFile {
    fn next_item(&mut self) -> Option<Item> {
        if self.done {
            return self.pending_fault.take().map(Item::Fault);
        }
        self.next_record_item()
    }
}
