//! ROS 2 CDR (XCDR1) byte reader. A message starts with a 4-byte encapsulation header
//! (`00 01` little-endian, `00 00` big-endian, then two option bytes); alignment of each
//! primitive is relative to the end of that header, i.e. to byte 4 of the message.

use super::wire::{Header, WireReader, WireResult, stamp_nanoseconds, stamp_seconds};

/// Bytes of the CDR encapsulation header.
const ENCAPSULATION_BYTES: usize = 4;

/// Cursor over one CDR-encoded message.
pub struct CdrReader<'a> {
    buf: &'a [u8],
    pos: usize,
    little: bool,
}

impl<'a> CdrReader<'a> {
    /// Reads the encapsulation header; plain CDR (`0x0000`/`0x0001`) and its parameter-list
    /// variants (`0x0002`/`0x0003`, same layout for final types) are accepted.
    pub fn new(buf: &'a [u8]) -> WireResult<Self> {
        if buf.len() < ENCAPSULATION_BYTES {
            return Err(format!(
                "CDR message of {} bytes is shorter than its 4-byte header",
                buf.len()
            ));
        }
        let little = match (buf[0], buf[1]) {
            (0, 0) | (0, 2) => false,
            (0, 1) | (0, 3) => true,
            (a, b) => {
                return Err(format!(
                    "unknown CDR encapsulation {a:#04x}{b:02x} (expected 0x0000..0x0003)"
                ));
            }
        };
        Ok(Self {
            buf,
            pos: ENCAPSULATION_BYTES,
            little,
        })
    }
}

impl<'a> WireReader<'a> for CdrReader<'a> {
    fn align(&mut self, size: usize) -> WireResult<()> {
        let rel = self.pos - ENCAPSULATION_BYTES;
        let pad = (size - rel % size) % size;
        self.bytes(pad).map(|_| ())
    }

    fn bytes(&mut self, n: usize) -> WireResult<&'a [u8]> {
        let end = self.pos.checked_add(n).filter(|&e| e <= self.buf.len());
        match end {
            Some(end) => {
                let out = &self.buf[self.pos..end];
                self.pos = end;
                Ok(out)
            }
            None => Err(format!(
                "message truncated: needs {n} bytes at offset {}, has {}",
                self.pos,
                self.buf.len()
            )),
        }
    }

    fn little_endian(&self) -> bool {
        self.little
    }

    fn string(&mut self) -> WireResult<String> {
        let n = self.seq_len(1)?;
        let raw = self.bytes(n)?;
        // The length counts the NUL terminator; tolerate writers that omit it.
        let text = raw.strip_suffix(&[0]).unwrap_or(raw);
        Ok(String::from_utf8_lossy(text).into_owned())
    }

    fn header(&mut self) -> WireResult<Header> {
        let sec = self.i32()?;
        let nanosec = self.u32()?;
        let frame_id = self.string()?;
        Ok(Header {
            stamp: stamp_seconds(i64::from(sec), nanosec),
            stamp_ns: stamp_nanoseconds(i64::from(sec), nanosec),
            frame_id,
        })
    }

    fn remaining(&self) -> usize {
        self.buf.len() - self.pos
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn alignment_is_relative_to_the_encapsulation_header() {
        // header LE, u8 = 7, pad 3, u32 = 5, pad 0, f64 (aligned at rel 8) = 1.5
        let mut buf = vec![0u8, 1, 0, 0, 7, 0xAA, 0xAA, 0xAA];
        buf.extend_from_slice(&5u32.to_le_bytes());
        buf.extend_from_slice(&1.5f64.to_le_bytes());
        let mut r = CdrReader::new(&buf).unwrap();
        assert_eq!(r.u8().unwrap(), 7);
        assert_eq!(r.u32().unwrap(), 5);
        assert_eq!(r.f64().unwrap(), 1.5);
        assert!(r.u8().is_err());
    }

    #[test]
    fn big_endian_strings_and_headers() {
        let mut buf = vec![0u8, 0, 0, 0];
        buf.extend_from_slice(&3i32.to_be_bytes());
        buf.extend_from_slice(&500_000_000u32.to_be_bytes());
        buf.extend_from_slice(&4u32.to_be_bytes());
        buf.extend_from_slice(b"map\0");
        let mut r = CdrReader::new(&buf).unwrap();
        let h = r.header().unwrap();
        assert_eq!(h.stamp, 3.5);
        assert_eq!(h.frame_id, "map");
    }
}
