//! Proptest fuzz of the message decoders and the container readers: arbitrary bytes, in both
//! encodings and for every message kind, or after each container's magic, give `Ok`, `Err`
//! or faults, never a panic (bounded cases so it runs in seconds; `examples/fuzz_logs.rs`
//! mutates real logs for minutes).

use proptest::prelude::*;

use super::messages::{MessageKind, decode_cloud, decode_imu_message, decode_poses};
use super::source::{Container, MessageSource};
use super::wire::Encoding;

const KINDS: [MessageKind; 7] = [
    MessageKind::PointCloud2,
    MessageKind::LivoxCustom,
    MessageKind::Odometry,
    MessageKind::PoseStamped,
    MessageKind::TransformStamped,
    MessageKind::TfMessage,
    MessageKind::Imu,
];

fn decode_any(kind: MessageKind, encoding: Encoding, data: &[u8]) {
    let _ = match kind {
        k if k.is_points() => decode_cloud(k, encoding, data).map(|_| ()),
        MessageKind::Imu => decode_imu_message(encoding, data).map(|_| ()),
        k => decode_poses(k, encoding, data).map(|_| ()),
    };
}

/// A valid little-endian CDR PointCloud2 prefix, so mutations reach the data path.
fn pointcloud_seed() -> Vec<u8> {
    let mut b = vec![0u8, 1, 0, 0];
    b.extend_from_slice(&[0; 8]); // stamp
    b.extend_from_slice(&1u32.to_le_bytes());
    b.push(0); // frame_id ""
    b.extend_from_slice(&[0; 3]);
    b.extend_from_slice(&1u32.to_le_bytes()); // height
    b.extend_from_slice(&2u32.to_le_bytes()); // width
    b.extend_from_slice(&3u32.to_le_bytes()); // fields
    for (i, name) in [b"x\0", b"y\0", b"z\0"].iter().enumerate() {
        b.extend_from_slice(&2u32.to_le_bytes());
        b.extend_from_slice(*name);
        b.extend_from_slice(&[0; 2]);
        b.extend_from_slice(&(4 * i as u32).to_le_bytes());
        b.push(7);
        b.extend_from_slice(&[0; 3]);
        b.extend_from_slice(&1u32.to_le_bytes());
    }
    b.push(0);
    b.extend_from_slice(&[0; 3]);
    b.extend_from_slice(&12u32.to_le_bytes());
    b.extend_from_slice(&24u32.to_le_bytes());
    b.extend_from_slice(&24u32.to_le_bytes());
    b.extend_from_slice(&[0x3f; 24]);
    b.push(1);
    b
}

#[test]
fn seed_decodes() {
    let c = decode_cloud(MessageKind::PointCloud2, Encoding::Cdr, &pointcloud_seed()).unwrap();
    assert_eq!(c.points.len(), 2);
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 20_000, ..ProptestConfig::default() })]

    #[test]
    fn arbitrary_bytes_never_panic(data in proptest::collection::vec(any::<u8>(), 0..256),
                                   kind in 0usize..7, ros1 in any::<bool>()) {
        let encoding = if ros1 { Encoding::Ros1 } else { Encoding::Cdr };
        decode_any(KINDS[kind], encoding, &data);
    }

    #[test]
    fn mutated_pointclouds_never_panic(flips in proptest::collection::vec((0usize..160, any::<u8>()), 1..8),
                                       cut in 0usize..200) {
        let mut data = pointcloud_seed();
        for (i, v) in flips {
            if let Some(b) = data.get_mut(i) { *b = v; }
        }
        data.truncate(cut.max(4));
        decode_any(MessageKind::PointCloud2, Encoding::Cdr, &data);
    }
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 2_000, ..ProptestConfig::default() })]

    #[test]
    fn arbitrary_container_bytes_never_panic(body in proptest::collection::vec(any::<u8>(), 0..1024),
                                             which in 0usize..2) {
        let (magic, container, ext): (&[u8], Container, &str) = match which {
            0 => (super::mcap_file::MCAP_MAGIC, Container::Mcap, "mcap"),
            _ => (super::bag::BAG_MAGIC, Container::Bag, "bag"),
        };
        let dir = std::env::temp_dir().join(format!("decod-fuzz-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join(format!("input-{:?}.{ext}", std::thread::current().id()));
        std::fs::write(&path, [magic, &body].concat()).unwrap();
        let mut source = MessageSource::new(vec![(path.clone(), container)]);
        let read = source.by_ref().take(10_000).count();
        drop(source);
        let _ = std::fs::remove_file(&path);
        let _ = std::fs::remove_dir(&dir);
        prop_assert!(read < 10_000);
    }
}
