//! Full verification of a log: every message read (chunk CRCs checked) and every message of a
//! type decod reads decoded. `decod convert` runs it on its output, so a conversion that
//! silently produced undecodable messages is caught at once.

use std::path::Path;

use super::log::log_files;
use super::messages::{MessageKind, decode_cloud, decode_imu_message, decode_poses};
use super::source::MessageSource;
use super::wire::Encoding;
use crate::error::Result;

/// Verification result of one topic.
#[derive(Clone, Debug, PartialEq)]
pub struct TopicCheck {
    /// Topic name.
    pub topic: String,
    /// Schema name as written.
    pub message_type: String,
    /// Whether decod decodes this type and encoding.
    pub supported: bool,
    /// Messages read.
    pub messages: u64,
    /// Messages decoded without error (0 for unsupported topics).
    pub decoded: u64,
    /// Finite points in the decoded clouds (point-cloud topics).
    pub points: u64,
    /// The first decode error, when there was one.
    pub first_error: Option<String>,
}

/// Reads and decodes every message of the log at `path`. A fault of the log itself
/// (truncation, corrupt chunk) is an error naming the file (the first fault, after reading
/// everything); decode failures are counted per
/// topic with the first one kept.
pub fn check(path: &Path) -> Result<Vec<TopicCheck>> {
    let mut topics: Vec<TopicCheck> = Vec::new();
    let mut source = MessageSource::new(log_files(path)?);
    for msg in source.by_ref() {
        let msg = msg?;
        let idx = match topics.iter().position(|t| t.topic == msg.channel.topic) {
            Some(i) => i,
            None => {
                let message_type = msg.channel.message_type.clone();
                let supported = MessageKind::from_type(&message_type).is_some()
                    && Encoding::from_mcap(&msg.channel.encoding).is_some();
                topics.push(TopicCheck {
                    topic: msg.channel.topic.clone(),
                    message_type,
                    supported,
                    messages: 0,
                    decoded: 0,
                    points: 0,
                    first_error: None,
                });
                topics.len() - 1
            }
        };
        let entry = &mut topics[idx];
        entry.messages += 1;
        let kind = MessageKind::from_type(&entry.message_type);
        let encoding = Encoding::from_mcap(&msg.channel.encoding);
        let (Some(kind), Some(encoding)) = (kind, encoding) else {
            continue;
        };
        let outcome = if kind.is_points() {
            decode_cloud(kind, encoding, &msg.data).map(|c| c.points.len() as u64)
        } else if kind == MessageKind::Imu {
            decode_imu_message(encoding, &msg.data).map(|_| 0)
        } else {
            decode_poses(kind, encoding, &msg.data).map(|_| 0)
        };
        match outcome {
            Ok(points) => {
                entry.decoded += 1;
                entry.points += points;
            }
            Err(e) if entry.first_error.is_none() => {
                entry.first_error = Some(format!(
                    "message at log time {:.9} s: {e}",
                    msg.log_time as f64 * 1e-9
                ));
            }
            Err(_) => {}
        }
    }
    if let Some(fault) = source.faults().first() {
        return Err(fault.to_error(None));
    }
    topics.sort_by(|a, b| a.topic.cmp(&b.topic));
    Ok(topics)
}
