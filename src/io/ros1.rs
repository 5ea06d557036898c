//! ROS 1 byte reader: packed little-endian, no alignment, strings without terminator,
//! `Header` = `seq: uint32, stamp: (sec: uint32, nsec: uint32), frame_id: string`.

use super::wire::{Header, WireReader, WireResult, stamp_nanoseconds, stamp_seconds};

/// Cursor over one ROS 1-serialised message.
pub struct Ros1Reader<'a> {
    buf: &'a [u8],
    pos: usize,
}

impl<'a> Ros1Reader<'a> {
    /// A reader at the start of `buf`.
    pub fn new(buf: &'a [u8]) -> Self {
        Self { buf, pos: 0 }
    }
}

impl<'a> WireReader<'a> for Ros1Reader<'a> {
    fn align(&mut self, _size: usize) -> WireResult<()> {
        Ok(())
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
        true
    }

    fn string(&mut self) -> WireResult<String> {
        let n = self.seq_len(1)?;
        Ok(String::from_utf8_lossy(self.bytes(n)?).into_owned())
    }

    fn header(&mut self) -> WireResult<Header> {
        let _seq = self.u32()?;
        let sec = self.u32()?;
        let nsec = self.u32()?;
        let frame_id = self.string()?;
        Ok(Header {
            stamp: stamp_seconds(i64::from(sec), nsec),
            stamp_ns: stamp_nanoseconds(i64::from(sec), nsec),
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
    fn header_has_seq_and_unterminated_string() {
        let mut buf = Vec::new();
        for v in [9u32, 2, 250_000_000, 4] {
            buf.extend_from_slice(&v.to_le_bytes());
        }
        buf.extend_from_slice(b"base");
        buf.extend_from_slice(&2.0f64.to_le_bytes());
        let mut r = Ros1Reader::new(&buf);
        let h = r.header().unwrap();
        assert_eq!((h.stamp, h.frame_id.as_str()), (2.25, "base"));
        assert_eq!(r.f64().unwrap(), 2.0);
        assert!(r.u8().is_err());
    }
}
