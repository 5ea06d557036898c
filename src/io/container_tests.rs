//! Tests of the three container readers on logs built here: complete, cut at every offset,
//! with a corrupt chunk; every cut yields a prefix of the complete log's messages and one
//! fault, never a panic.

use std::collections::BTreeMap;
use std::io::Write;
use std::path::{Path, PathBuf};

use super::source::{Container, FaultKind, LogFault, MessageSource};

/// A fresh path in the system temp directory (unique per test and name), removed with its
/// directory (once empty) when the test is done.
fn temp_path(name: &str) -> TempFile {
    let dir = std::env::temp_dir().join(format!("decod-io-tests-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    TempFile(dir.join(name))
}

/// A test's file, removed on drop (the directory too once no other test's file is in it).
struct TempFile(PathBuf);

impl std::ops::Deref for TempFile {
    type Target = Path;
    fn deref(&self) -> &Path {
        &self.0
    }
}

impl AsRef<Path> for TempFile {
    fn as_ref(&self) -> &Path {
        &self.0
    }
}

impl Drop for TempFile {
    fn drop(&mut self) {
        let _ = std::fs::remove_file(&self.0);
        if let Some(dir) = self.0.parent() {
            let _ = std::fs::remove_dir(dir);
        }
    }
}

/// `(log_time, data)` of every message, and the faults.
fn read(path: &Path, container: Container) -> (Vec<(u64, Vec<u8>)>, Vec<LogFault>) {
    let mut source = MessageSource::new(vec![(path.to_path_buf(), container)]);
    let msgs = source.by_ref().map(|m| m.map(|m| (m.log_time, m.data)));
    let msgs: Vec<_> = msgs.collect::<Result<_, _>>().unwrap_or_default();
    (msgs, source.faults().to_vec())
}

fn payload(k: u64) -> Vec<u8> {
    (0..200 + k * 13).map(|i| (i * 7 + k) as u8).collect()
}

fn mcap_bytes(compression: Option<mcap::Compression>) -> Vec<u8> {
    mcap_bytes_on(&["/chatter"], compression)
}

/// Twenty messages on each of `topics` in turn (topic `i` carries `payload(k + i)`), in
/// 1 KB chunks.
fn mcap_bytes_on(topics: &[&str], compression: Option<mcap::Compression>) -> Vec<u8> {
    let mut out = std::io::Cursor::new(Vec::new());
    let mut w = mcap::WriteOptions::new()
        .compression(compression)
        .chunk_size(Some(1024))
        .create(&mut out)
        .unwrap();
    let schema = w
        .add_schema("std_msgs/String", "ros1msg", b"string data")
        .unwrap();
    let channels: Vec<u16> = topics
        .iter()
        .map(|t| w.add_channel(schema, t, "ros1", &BTreeMap::new()).unwrap())
        .collect();
    for k in 0..20u64 {
        for (i, &channel_id) in channels.iter().enumerate() {
            let header = mcap::records::MessageHeader {
                channel_id,
                sequence: k as u32,
                log_time: 1_000 + k,
                publish_time: 1_000 + k,
            };
            w.write_to_known_channel(&header, &payload(k + i as u64))
                .unwrap();
        }
    }
    w.finish().unwrap();
    drop(w);
    out.into_inner()
}

/// Every cut of `bytes` reads a prefix of the complete log and reports one fault.
fn check_every_cut(bytes: &[u8], container: Container, name: &str, step: usize) {
    let path = temp_path(name);
    std::fs::write(&path, bytes).unwrap();
    let (full, faults) = read(&path, container);
    assert_eq!((full.len(), faults.len()), (20, 0), "{faults:?}");
    for cut in (0..bytes.len()).step_by(step) {
        std::fs::write(&path, &bytes[..cut]).unwrap();
        let mut source = MessageSource::new(vec![(path.to_path_buf(), container)]);
        let msgs: Vec<_> = source.by_ref().filter_map(|m| m.ok()).collect();
        assert!(msgs.len() <= full.len(), "cut {cut}");
        for (m, f) in msgs.iter().zip(&full) {
            assert_eq!((m.log_time, &m.data), (f.0, &f.1), "cut {cut}");
        }
        let faults = source.faults();
        assert!(
            faults.iter().any(|f| f.kind == FaultKind::Truncated),
            "cut {cut}: {faults:?}"
        );
        assert!(
            faults.iter().all(|f| f.offset <= cut as u64),
            "cut {cut}: {faults:?}"
        );
    }
}

#[test]
fn mcap_cut_at_every_offset_keeps_a_prefix() {
    for (k, c) in [
        None,
        Some(mcap::Compression::Zstd),
        Some(mcap::Compression::Lz4),
    ]
    .into_iter()
    .enumerate()
    {
        check_every_cut(&mcap_bytes(c), Container::Mcap, &format!("cut{k}.mcap"), 3);
    }
}

#[test]
fn mcap_corrupt_chunk_is_skipped_with_its_span_and_count() {
    let mut bytes = mcap_bytes(Some(mcap::Compression::Zstd));
    // The fourth chunk record's compressed data (opcode 0x06 at record boundaries).
    let mut at = 8;
    let mut chunks = Vec::new();
    while at + 9 <= bytes.len() {
        let len = u64::from_le_bytes(bytes[at + 1..at + 9].try_into().unwrap()) as usize;
        if bytes[at] == 0x06 {
            chunks.push(at);
        }
        at += 9 + len;
    }
    assert!(chunks.len() > 5);
    let victim = chunks[3] + 9 + 28 + 4 + 4 + 8 + 12;
    for b in &mut bytes[victim..victim + 8] {
        *b ^= 0x5a;
    }
    let path = temp_path("corrupt.mcap");
    std::fs::write(&path, &bytes).unwrap();
    let (msgs, faults) = read(&path, Container::Mcap);
    assert_eq!(faults.len(), 1, "{faults:?}");
    let fault = &faults[0];
    assert_eq!(fault.kind, FaultKind::Corrupt);
    let lost = fault.messages_lost.unwrap();
    let (t0, t1) = fault.lost_span_ns.unwrap();
    assert_eq!(msgs.len() as u64 + lost, 20);
    assert!(msgs.iter().all(|(t, _)| *t < t0 || *t > t1));
    assert_eq!(msgs.last().unwrap().0, 1_019);
    assert!(fault.to_string().contains("corrupt.mcap: corrupt at byte"));
}

/// The `len, name=value` fields of a ROS 1 bag record header.
fn bag_fields(fields: &[(&str, &[u8])]) -> Vec<u8> {
    let mut out = Vec::new();
    for (name, value) in fields {
        let field = [name.as_bytes(), b"=", value].concat();
        out.extend_from_slice(&(field.len() as u32).to_le_bytes());
        out.extend_from_slice(&field);
    }
    out
}

/// One ROS 1 bag record.
fn bag_record(fields: &[(&str, &[u8])], data: &[u8]) -> Vec<u8> {
    let header = bag_fields(fields);
    let mut out = (header.len() as u32).to_le_bytes().to_vec();
    out.extend_from_slice(&header);
    out.extend_from_slice(&(data.len() as u32).to_le_bytes());
    out.extend_from_slice(data);
    out
}

fn compress(fmt: &str, raw: &[u8]) -> Vec<u8> {
    match fmt {
        "bz2" => {
            let mut e = bzip2::write::BzEncoder::new(Vec::new(), bzip2::Compression::fast());
            e.write_all(raw).unwrap();
            e.finish().unwrap()
        }
        "lz4" => {
            let mut e = lz4::EncoderBuilder::new().build(Vec::new()).unwrap();
            e.write_all(raw).unwrap();
            let (out, result) = e.finish();
            result.unwrap();
            out
        }
        _ => raw.to_vec(),
    }
}

fn bag_time(sec: u64) -> Vec<u8> {
    [(sec as u32).to_le_bytes(), 0u32.to_le_bytes()].concat()
}

/// A closed bag: 4 chunks of 5 messages each (`fmt` compression), each followed by its
/// index data record; connection and chunk-info records at `index_pos`.
fn bag_bytes(fmt: &str) -> Vec<u8> {
    let conn = 0u32.to_le_bytes();
    let type_fields = bag_fields(&[("type", b"std_msgs/String"), ("md5sum", b"0")]);
    let connection = bag_record(
        &[("op", &[0x07]), ("conn", &conn), ("topic", b"/chatter")],
        &type_fields,
    );
    let chunk_count = 4u32.to_le_bytes();
    let bag_header = |index_pos: &[u8]| {
        let fields: [(&str, &[u8]); 3] = [
            ("op", &[0x03]),
            ("index_pos", index_pos),
            ("chunk_count", &chunk_count),
        ];
        bag_record(&fields, &[b' '; 4])
    };
    let header_len = bag_header(&[0; 8]).len();
    let start = super::bag::BAG_MAGIC.len() + header_len;
    let (mut chunks, mut infos) = (Vec::new(), Vec::new());
    for c in 0..4u64 {
        let mut raw = if c == 0 {
            connection.clone()
        } else {
            Vec::new()
        };
        for k in c * 5..c * 5 + 5 {
            let fields: [(&str, &[u8]); 3] = [
                ("op", &[0x02]),
                ("conn", &conn),
                ("time", &bag_time(1_000 + k)),
            ];
            raw.extend(bag_record(&fields, &payload(k)));
        }
        let size = (raw.len() as u32).to_le_bytes();
        let pos = ((start + chunks.len()) as u64).to_le_bytes();
        let fields: [(&str, &[u8]); 3] = [
            ("op", &[0x05]),
            ("compression", fmt.as_bytes()),
            ("size", &size),
        ];
        chunks.extend(bag_record(&fields, &compress(fmt, &raw)));
        let count = 5u32.to_le_bytes();
        let index: [(&str, &[u8]); 4] = [
            ("op", &[0x04]),
            ("ver", &1u32.to_le_bytes()),
            ("conn", &conn),
            ("count", &count),
        ];
        chunks.extend(bag_record(&index, &[0; 60]));
        let (t0, t1) = (bag_time(1_000 + c * 5), bag_time(1_004 + c * 5));
        let info: [(&str, &[u8]); 6] = [
            ("op", &[0x06]),
            ("ver", &1u32.to_le_bytes()),
            ("chunk_pos", &pos),
            ("start_time", &t0),
            ("end_time", &t1),
            ("count", &1u32.to_le_bytes()),
        ];
        infos.extend(bag_record(&info, &[conn, count].concat()));
    }
    let mut out = super::bag::BAG_MAGIC.to_vec();
    let index_pos = ((start + chunks.len()) as u64).to_le_bytes();
    out.extend(bag_header(&index_pos));
    out.extend(chunks);
    out.extend(connection);
    out.extend(infos);
    out
}

#[test]
fn bag_cut_at_every_offset_keeps_a_prefix() {
    for fmt in ["none", "bz2", "lz4"] {
        check_every_cut(
            &bag_bytes(fmt),
            Container::Bag,
            &format!("cut-{fmt}.bag"),
            5,
        );
    }
}

#[test]
fn bag_corrupt_chunk_is_skipped_and_counted_from_the_index() {
    let mut bytes = bag_bytes("bz2");
    let second = bytes
        .windows(4)
        .filter(|w| w == b"BZh1")
        .nth(1)
        .map(|w| w.as_ptr());
    let at = second.unwrap() as usize - bytes.as_ptr() as usize + 20;
    bytes[at] ^= 0xff;
    let path = temp_path("corrupt.bag");
    std::fs::write(&path, &bytes).unwrap();
    let (msgs, faults) = read(&path, Container::Bag);
    assert_eq!(faults.len(), 1, "{faults:?}");
    assert_eq!(
        (faults[0].kind, faults[0].messages_lost),
        (FaultKind::Corrupt, Some(5))
    );
    let times: Vec<u64> = msgs.iter().map(|m| m.0 / 1_000_000_000).collect();
    assert_eq!(
        times,
        [
            1000, 1001, 1002, 1003, 1004, 1010, 1011, 1012, 1013, 1014, 1015, 1016, 1017, 1018,
            1019
        ]
    );
    let (topics, start, end) = super::bag::bag_summary(&path).unwrap().unwrap();
    assert_eq!(
        (topics[0].topic.as_str(), topics[0].count),
        ("/chatter", 20)
    );
    assert_eq!(
        (start, end),
        (Some(1_000_000_000_000), Some(1_019_000_000_000))
    );
}

#[test]
fn db3_reads_in_row_order_and_refuses_other_files() {
    let path = temp_path("log.db3");
    let _ = std::fs::remove_file(&path);
    let db = rusqlite::Connection::open(&path).unwrap();
    db.execute_batch(
        "CREATE TABLE topics(id INTEGER PRIMARY KEY, name TEXT, type TEXT, serialization_format TEXT, offered_qos_profiles TEXT);
         CREATE TABLE messages(id INTEGER PRIMARY KEY, topic_id INTEGER, timestamp INTEGER, data BLOB);
         INSERT INTO topics VALUES (1, '/chatter', 'std_msgs/msg/String', 'cdr', '');",
    )
    .unwrap();
    for k in 0..20u64 {
        db.execute(
            "INSERT INTO messages(topic_id, timestamp, data) VALUES (1, ?1, ?2)",
            (1_000 + k as i64, payload(k)),
        )
        .unwrap();
    }
    drop(db);
    let (msgs, faults) = read(&path, Container::Db3);
    assert!(faults.is_empty());
    assert_eq!(msgs.len(), 20);
    assert!(
        msgs.iter()
            .enumerate()
            .all(|(k, m)| m.0 == 1_000 + k as u64 && m.1 == payload(k as u64))
    );
    let (topics, start, end) = super::db3::db3_summary(&path).unwrap();
    assert_eq!(
        (topics[0].count, start, end),
        (20, Some(1_000), Some(1_019))
    );
    let not_a_bag = temp_path("notes.db3");
    std::fs::write(&not_a_bag, b"SQLite format 3\0 but nothing else").unwrap();
    let mut source = MessageSource::new(vec![(not_a_bag.to_path_buf(), Container::Db3)]);
    assert!(source.next().unwrap().is_err());
}

#[test]
fn mcap_payload_filter_empties_only_the_rejected_channels() {
    // Two channels in 1 KB chunks: the filter keeps /chatter's payloads, the other
    // channel's messages come with empty data and the same times and count.
    let path = temp_path("payload_filter.mcap");
    std::fs::write(&path, mcap_bytes_on(&["/chatter", "/points"], None)).unwrap();
    let filter: super::source::PayloadFilter =
        std::sync::Arc::new(|c: &super::source::ChannelMeta| c.topic == "/chatter");
    let mut source =
        MessageSource::new(vec![(path.to_path_buf(), Container::Mcap)]).with_payloads(filter);
    let msgs: Vec<_> = source.by_ref().map(|m| m.unwrap()).collect();
    assert!(source.faults().is_empty(), "{:?}", source.faults());
    assert_eq!(msgs.len(), 40);
    for m in &msgs {
        let k = m.log_time - 1_000;
        if m.channel.topic == "/chatter" {
            assert_eq!(m.data, payload(k));
        } else {
            assert!(m.data.is_empty());
        }
    }
    // Without a filter every payload is read.
    let (all, faults) = read(&path, Container::Mcap);
    assert!(faults.is_empty());
    assert!(all.iter().all(|(_, d)| !d.is_empty()));
    std::fs::remove_file(&path).unwrap();
}
