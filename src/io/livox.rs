//! livox_ros_driver/CustomMsg and livox_ros_driver2/CustomMsg (same layout): GEODE's Livox
//! device publishes only this, not PointCloud2.
//!
//! `header, timebase: uint64, point_num: uint32, lidar_id: uint8, rsvd: uint8[3],
//! points: CustomPoint[]` with `CustomPoint = offset_time: uint32, x y z: float32,
//! reflectivity tag line: uint8` (19 bytes packed in ROS 1; CDR pads each to 20).

use super::pointcloud::Cloud;
use super::wire::{WireReader, WireResult};
use crate::deskew::TimeKind;

/// Smallest serialised CustomPoint (ROS 1, packed).
const MIN_POINT_BYTES: usize = 19;

/// Decodes a Livox CustomMsg into a [`Cloud`] (stamp = header stamp; non-finite points
/// dropped and counted). The per-point `offset_time` (ns from `timebase`) is the time field.
pub fn decode_custom_msg<'a, R: WireReader<'a>>(r: &mut R) -> WireResult<Cloud> {
    let header = r.header()?;
    let timebase = r.u64()?;
    let _point_num = r.u32()?;
    let _lidar_id = r.u8()?;
    r.bytes(3)?;
    let n = r.seq_len(MIN_POINT_BYTES)?;
    let mut points = Vec::with_capacity(n);
    let mut times = Vec::with_capacity(n);
    let mut dropped = 0usize;
    // A point's time since the header stamp, ns: `timebase` (ns) is the first point's time.
    let base = i64::try_from(timebase)
        .ok()
        .and_then(|t| t.checked_sub(header.stamp_ns))
        .map_or(f64::INFINITY, |d| d as f64);
    for _ in 0..n {
        let offset_time = r.u32()?;
        let p = [r.f32()?, r.f32()?, r.f32()?];
        r.bytes(3)?;
        if p.iter().all(|v| v.is_finite()) {
            points.push(p);
            times.push(base + f64::from(offset_time));
        } else {
            dropped += 1;
        }
    }
    Ok(Cloud {
        header,
        points,
        dropped_non_finite: dropped,
        time_field: Some("offset_time".into()),
        times,
        time_kind: Some(TimeKind::Nanoseconds),
        has_intensity: true,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::io::cdr::CdrReader;

    #[test]
    fn cdr_points_are_padded_to_four_bytes() {
        let mut b = vec![0u8, 1, 0, 0];
        b.extend_from_slice(&5i32.to_le_bytes());
        b.extend_from_slice(&0u32.to_le_bytes());
        b.extend_from_slice(&1u32.to_le_bytes());
        b.extend_from_slice(&[0, 0, 0, 0]); // "" + pad to 8 (rel offset 13 -> 16)
        b.extend_from_slice(&7u64.to_le_bytes());
        b.extend_from_slice(&2u32.to_le_bytes());
        b.extend_from_slice(&[1, 0, 0, 0]);
        b.extend_from_slice(&2u32.to_le_bytes());
        for k in 0..2u32 {
            b.extend_from_slice(&k.to_le_bytes());
            for v in [1.0f32, 2.0, k as f32] {
                b.extend_from_slice(&v.to_le_bytes());
            }
            b.extend_from_slice(&[9, 0, 1, 0]);
        }
        let c = decode_custom_msg(&mut CdrReader::new(&b).unwrap()).unwrap();
        assert_eq!(c.points, vec![[1.0, 2.0, 0.0], [1.0, 2.0, 1.0]]);
        assert_eq!(c.header.stamp, 5.0);
    }
}
