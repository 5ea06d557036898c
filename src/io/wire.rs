//! The common interface of the two byte readers ([`super::cdr::CdrReader`] for ROS 2,
//! [`super::ros1::Ros1Reader`] for ROS 1), so that each message decoder is written once.
//!
//! Decoders return a plain `String` reason on failure; the caller, which knows the file and
//! topic, wraps it into [`crate::DecodError::Log`].

/// Result of a low-level decode step: the error is a human-readable reason.
pub type WireResult<T> = std::result::Result<T, String>;

/// The wire encoding of a channel's messages.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Encoding {
    /// ROS 2 CDR (XCDR1, `cdr` message encoding), little- or big-endian per message.
    Cdr,
    /// ROS 1 serialisation (`ros1` message encoding): packed little-endian, no alignment.
    Ros1,
}

impl Encoding {
    /// Maps an MCAP `message_encoding` to an [`Encoding`], `None` when decod cannot read it.
    pub fn from_mcap(message_encoding: &str) -> Option<Self> {
        match message_encoding {
            "cdr" => Some(Self::Cdr),
            "ros1" => Some(Self::Ros1),
            _ => None,
        }
    }
}

/// A std_msgs/Header: stamp in seconds and the frame id.
#[derive(Clone, Debug, PartialEq)]
pub struct Header {
    /// `stamp.sec + 1e-9 stamp.nanosec`, seconds.
    pub stamp: f64,
    /// The same stamp in whole nanoseconds, exactly (a driver's per-point times are reckoned
    /// in them: `crate::io::livox`).
    pub stamp_ns: i64,
    /// `frame_id`.
    pub frame_id: String,
}

/// Sequential reader of one serialised message. Every read is bounds-checked: truncated or
/// garbage bytes give an error, never a panic.
pub trait WireReader<'a> {
    /// Skips padding so that the next primitive of `size` bytes is aligned (CDR only).
    fn align(&mut self, size: usize) -> WireResult<()>;
    /// `n` raw bytes (no alignment).
    fn bytes(&mut self, n: usize) -> WireResult<&'a [u8]>;
    /// Whether multi-byte primitives are little-endian.
    fn little_endian(&self) -> bool;
    /// A string (length-prefixed; CDR includes a NUL terminator, ROS 1 does not).
    fn string(&mut self) -> WireResult<String>;
    /// A std_msgs/Header (ROS 1 has a leading `seq: uint32`).
    fn header(&mut self) -> WireResult<Header>;
    /// Bytes left after the cursor.
    fn remaining(&self) -> usize;

    /// A primitive of `N` bytes, aligned, in message byte order (returned as LE bytes).
    fn prim<const N: usize>(&mut self) -> WireResult<[u8; N]> {
        self.align(N)?;
        let raw = self.bytes(N)?;
        let mut out = [0u8; N];
        out.copy_from_slice(raw);
        if !self.little_endian() {
            out.reverse();
        }
        Ok(out)
    }
    /// `uint8` / `bool`.
    fn u8(&mut self) -> WireResult<u8> {
        Ok(self.prim::<1>()?[0])
    }
    /// `uint32`.
    fn u32(&mut self) -> WireResult<u32> {
        Ok(u32::from_le_bytes(self.prim::<4>()?))
    }
    /// `int32`.
    fn i32(&mut self) -> WireResult<i32> {
        Ok(i32::from_le_bytes(self.prim::<4>()?))
    }
    /// `uint64`.
    fn u64(&mut self) -> WireResult<u64> {
        Ok(u64::from_le_bytes(self.prim::<8>()?))
    }
    /// `float32`.
    fn f32(&mut self) -> WireResult<f32> {
        Ok(f32::from_le_bytes(self.prim::<4>()?))
    }
    /// `float64`.
    fn f64(&mut self) -> WireResult<f64> {
        Ok(f64::from_le_bytes(self.prim::<8>()?))
    }
    /// Length of a variable-size sequence, checked against the bytes left (each element
    /// takes at least `min_element_bytes`), so garbage lengths fail before allocating.
    fn seq_len(&mut self, min_element_bytes: usize) -> WireResult<usize> {
        let n = self.u32()? as usize;
        if n.saturating_mul(min_element_bytes.max(1)) > self.remaining() && min_element_bytes > 0 {
            return Err(format!(
                "sequence of {n} elements does not fit in the {} bytes left",
                self.remaining()
            ));
        }
        Ok(n)
    }
    /// `float64[N]` fixed array, values discarded.
    fn skip_f64s(&mut self, n: usize) -> WireResult<()> {
        for _ in 0..n {
            self.f64()?;
        }
        Ok(())
    }
    /// geometry_msgs/Vector3 or Point.
    fn vec3(&mut self) -> WireResult<[f64; 3]> {
        Ok([self.f64()?, self.f64()?, self.f64()?])
    }
    /// geometry_msgs/Quaternion `(x, y, z, w)`.
    fn quat(&mut self) -> WireResult<[f64; 4]> {
        Ok([self.f64()?, self.f64()?, self.f64()?, self.f64()?])
    }
}

/// Seconds from a ROS time `(sec, nanosec)`.
pub fn stamp_seconds(sec: i64, nanosec: u32) -> f64 {
    sec as f64 + f64::from(nanosec) * 1e-9
}

/// Nanoseconds from a ROS time `(sec, nanosec)` (saturating beyond the year 2262).
pub fn stamp_nanoseconds(sec: i64, nanosec: u32) -> i64 {
    sec.saturating_mul(1_000_000_000)
        .saturating_add(i64::from(nanosec))
}
