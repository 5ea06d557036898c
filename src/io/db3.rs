//! rosbag2 sqlite3 storage (`.db3`, the default of ROS 2 Foxy to Humble) read natively
//! (issue 11) through rusqlite with SQLite bundled: no system library to match, and the
//! same binary reads every bag. Tables: `topics(id, name, type, serialization_format, ...)`
//! and `messages(id, topic_id, timestamp, data)`.
//!
//! Messages are read in row order (insertion = file order, as for MCAP) in pages of at most
//! [`PAGE_ROWS`] rows or [`PAGE_BYTES`] bytes, so memory stays bounded by a page however
//! large the bag. A database error mid-read (a damaged page) ends the file with a
//! [`FaultKind::Unreadable`] fault naming the last row read; every message before stays.

use std::collections::{HashMap, VecDeque};
use std::path::{Path, PathBuf};
use std::sync::Arc;

use rusqlite::{Connection, OpenFlags};

use super::log::{FileSummary, TopicInfo, log_error};
use super::source::{ChannelMeta, ContainerReader, FaultKind, Item, LogFault, RawMessage};
use crate::error::Result;

/// Rows fetched per query.
const PAGE_ROWS: i64 = 64;
/// A page stops early once its messages hold this many bytes (clouds are MB-sized).
const PAGE_BYTES: usize = 64 << 20;

/// The first 16 bytes of an SQLite database.
pub const SQLITE_MAGIC: &[u8; 16] = b"SQLite format 3\0";

fn db_error(path: &Path, e: &rusqlite::Error) -> crate::error::DecodError {
    log_error(
        path,
        None,
        format!("not a readable rosbag2 sqlite3 database: {e}"),
    )
}

fn connect(path: &Path) -> Result<Connection> {
    let flags = OpenFlags::SQLITE_OPEN_READ_ONLY | OpenFlags::SQLITE_OPEN_NO_MUTEX;
    Connection::open_with_flags(path, flags).map_err(|e| db_error(path, &e))
}

/// The topics table: id -> channel.
fn channels(path: &Path, db: &Connection) -> Result<HashMap<i64, Arc<ChannelMeta>>> {
    let mut stmt = db
        .prepare("SELECT id, name, type, serialization_format FROM topics")
        .map_err(|e| db_error(path, &e))?;
    let rows = stmt
        .query_map([], |row| {
            let meta = ChannelMeta {
                topic: row.get(1)?,
                message_type: row.get(2)?,
                encoding: row.get(3)?,
            };
            Ok((row.get::<_, i64>(0)?, Arc::new(meta)))
        })
        .map_err(|e| db_error(path, &e))?;
    rows.collect::<rusqlite::Result<_>>()
        .map_err(|e| db_error(path, &e))
}

/// A reader of one `.db3` file (see the module doc).
pub struct Db3File {
    path: PathBuf,
    db: Connection,
    channels: HashMap<i64, Arc<ChannelMeta>>,
    page: VecDeque<RawMessage>,
    last_id: i64,
    last_time: Option<u64>,
    done: bool,
}

impl Db3File {
    /// Opens the database read-only and reads its topics table.
    pub fn open(path: &Path) -> Result<Self> {
        let db = connect(path)?;
        let channels = channels(path, &db)?;
        Ok(Self {
            path: path.to_path_buf(),
            db,
            channels,
            page: VecDeque::new(),
            last_id: i64::MIN,
            last_time: None,
            done: false,
        })
    }

    /// Fetches the next page of messages after `last_id`; `Ok(false)` when there are none.
    fn fetch(&mut self) -> rusqlite::Result<bool> {
        let mut stmt = self.db.prepare_cached(
            "SELECT id, topic_id, timestamp, data FROM messages WHERE id > ?1 ORDER BY id LIMIT ?2",
        )?;
        let mut rows = stmt.query((self.last_id, PAGE_ROWS))?;
        let mut bytes = 0usize;
        while let Some(row) = rows.next()? {
            let id: i64 = row.get(0)?;
            let topic_id: i64 = row.get(1)?;
            let stamp: i64 = row.get(2)?;
            self.last_id = id;
            let Some(channel) = self.channels.get(&topic_id) else {
                continue;
            };
            let data = row.get_ref(3)?.as_blob()?.to_vec();
            bytes += data.len();
            self.page.push_back(RawMessage {
                channel: channel.clone(),
                log_time: u64::try_from(stamp).unwrap_or(0),
                data,
                file: 0,
            });
            if bytes >= PAGE_BYTES {
                break;
            }
        }
        Ok(!self.page.is_empty())
    }
}

impl ContainerReader for Db3File {
    fn next_item(&mut self) -> Option<Item> {
        if self.page.is_empty() && !self.done {
            match self.fetch() {
                Ok(true) => {}
                Ok(false) => self.done = true,
                Err(e) => {
                    self.done = true;
                    return Some(Item::Fault(LogFault::new(
                        &self.path,
                        FaultKind::Unreadable,
                        u64::try_from(self.last_id).unwrap_or(0),
                        format!("database error after row {}: {e}", self.last_id),
                        self.last_time,
                    )));
                }
            }
        }
        let msg = self.page.pop_front()?;
        self.last_time = Some(msg.log_time);
        Some(Item::Message(msg))
    }
}

/// Topics, counts and time span of a `.db3` file by SQL (no message is read).
pub fn db3_summary(path: &Path) -> Result<FileSummary> {
    let db = connect(path)?;
    let channels = channels(path, &db)?;
    let mut stmt = db
        .prepare(
            "SELECT topic_id, COUNT(*), MIN(timestamp), MAX(timestamp) FROM messages \
             GROUP BY topic_id",
        )
        .map_err(|e| db_error(path, &e))?;
    let counts: Vec<(i64, i64, i64, i64)> = stmt
        .query_map([], |r| Ok((r.get(0)?, r.get(1)?, r.get(2)?, r.get(3)?)))
        .and_then(|rows| rows.collect())
        .map_err(|e| db_error(path, &e))?;
    let mut topics: Vec<TopicInfo> = Vec::new();
    let (mut start, mut end): (Option<u64>, Option<u64>) = (None, None);
    for (id, meta) in &channels {
        let row = counts.iter().find(|c| c.0 == *id);
        let count = row.map_or(0, |c| u64::try_from(c.1).unwrap_or(0));
        if let Some(&(_, _, t0, t1)) = row {
            let (t0, t1) = (
                u64::try_from(t0).unwrap_or(0),
                u64::try_from(t1).unwrap_or(0),
            );
            start = Some(start.map_or(t0, |s| s.min(t0)));
            end = Some(end.map_or(t1, |e| e.max(t1)));
        }
        match topics.iter_mut().find(|t| t.topic == meta.topic) {
            Some(t) => t.count += count,
            None => topics.push(TopicInfo {
                topic: meta.topic.clone(),
                message_type: meta.message_type.clone(),
                encoding: meta.encoding.clone(),
                count,
            }),
        }
    }
    Ok((topics, start, end))
}
