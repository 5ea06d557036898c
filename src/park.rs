//! Landmarks set aside on disk while a run rebuilds its submaps (beyond the paper).
//!
//! A run whose first correction stitches the submaps differently enough extracts, matches and
//! optimises again on submaps rebuilt on it (`decod_rs.stages.refine`), and keeps the earlier
//! round in case the rebuilt one does not stand. The earlier round's landmarks (about 29 KB
//! each: the offsets, the mask, the contour) were held beside the rebuilt ones and their
//! prepared views, the peak of a long log's run; set aside here, they come back exactly when
//! the earlier round is needed again (a record holds what a landmark holds: the offsets in
//! f32, as in a survey).
//!
//! **Format** (a temporary file the run writes and reads itself; little-endian, no code):
//! magic `DECODPRK`, version u32 [`FORMAT_VERSION`], count u64, then `count` records, each
//! its length in bytes (u64) and a survey record (`crate::survey`). Version 1 stored the
//! offsets in f64, when a landmark held them so.
//! Read one record at a time into one buffer (the whole file at once was 0.4 GB on top of the
//! rebuilt round for a 400 m pipe), every length checked against the bytes left in the file
//! before anything is allocated.

use std::fs::File;
use std::io::{BufReader, Read};
use std::path::Path;

use crate::error::{DecodError, Result};
use crate::landmark::Landmark;
use crate::survey::{MIN_RECORD_BYTES, Reader, Source, err, write_records};

/// File magic.
pub const MAGIC: &[u8; 8] = b"DECODPRK";
/// Current format version; reading any other is an error.
pub const FORMAT_VERSION: u32 = 2;

/// Bytes before the first record: magic, version, count.
const HEAD_BYTES: u64 = 20;

/// Writes `landmarks` to `path`, exactly.
pub fn write<L: Source>(path: &Path, landmarks: &[L]) -> Result<()> {
    let mut head = Vec::with_capacity(HEAD_BYTES as usize);
    head.extend_from_slice(MAGIC);
    head.extend_from_slice(&FORMAT_VERSION.to_le_bytes());
    head.extend_from_slice(&(landmarks.len() as u64).to_le_bytes());
    write_records(path, &head, landmarks, true)
}

/// Reads the landmarks [`write`] wrote to `path`, in their order; a foreign, truncated or
/// inconsistent file is a [`DecodError::Database`] saying which.
pub fn read(path: &Path) -> Result<Vec<Landmark>> {
    let io = |source| DecodError::Io {
        path: path.to_path_buf(),
        source,
    };
    let file = File::open(path).map_err(io)?;
    let size = file.metadata().map_err(io)?.len();
    let mut file = BufReader::new(file);
    let mut take = |n: usize, buf: &mut Vec<u8>| -> Result<()> {
        buf.resize(n, 0);
        file.read_exact(buf)
            .map_err(|e| err(path, format!("truncated: {e}")))
    };
    let mut buf = Vec::new();
    if size < HEAD_BYTES {
        return Err(err(
            path,
            "not landmarks set aside by decod (shorter than a DECODPRK header)",
        ));
    }
    take(HEAD_BYTES as usize, &mut buf)?;
    let mut head = Reader::new(&buf, path);
    if head.take(8).ok() != Some(&MAGIC[..]) {
        return Err(err(
            path,
            "not landmarks set aside by decod (no DECODPRK magic)",
        ));
    }
    let version = head.u32()?;
    if version != FORMAT_VERSION {
        return Err(err(
            path,
            format!("format version {version}, not {FORMAT_VERSION}"),
        ));
    }
    let count = head.u64()?;
    let mut left = size - HEAD_BYTES;
    if count > left / (8 + MIN_RECORD_BYTES) {
        return Err(err(
            path,
            format!("{count} landmarks cannot fit in the file"),
        ));
    }
    let mut landmarks = Vec::with_capacity(count as usize);
    for k in 0..count as usize {
        let at = |e: DecodError| err(path, format!("landmark {k}: {e}"));
        take(8, &mut buf).map_err(at)?;
        let n = Reader::new(&buf, path).u64().map_err(at)?;
        left -= 8;
        if n > left || n < MIN_RECORD_BYTES {
            return Err(at(err(
                path,
                format!("a record of {n} bytes with {left} left"),
            )));
        }
        left -= n;
        take(n as usize, &mut buf).map_err(at)?;
        let mut r = Reader::new(&buf, path);
        let l = r.landmark().map_err(at)?;
        if r.left() != 0 {
            return Err(at(err(
                path,
                format!("{} bytes beyond the record", r.left()),
            )));
        }
        l.validate().map_err(at)?;
        landmarks.push(l);
    }
    if left != 0 {
        return Err(err(path, format!("{left} unexpected bytes at the end")));
    }
    Ok(landmarks)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::matching::synthetic::{Grid, JointSurface, Observation, Rng, SurfaceParams};

    #[test]
    fn landmarks_come_back_exactly_and_damage_is_refused() {
        let g = Grid::tunnel();
        let mut rng = Rng::new(9);
        let landmarks: Vec<Landmark> = (0..3u64)
            .map(|k| {
                JointSurface::new(g, SurfaceParams::for_grid(&g), 1, k)
                    .observe(&Observation::random(&g, k as f64, false, &mut rng), k)
            })
            .collect();
        let dir = std::env::temp_dir().join(format!("decod-park-{}", std::process::id()));
        std::fs::create_dir_all(&dir).ok();
        let path = dir.join("first.park");
        assert!(write(&path, &landmarks).is_ok());
        let back = read(&path).unwrap_or_default();
        assert_eq!(back.len(), 3);
        for (a, b) in landmarks.iter().zip(&back) {
            let bits = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
            assert_eq!(bits(&a.descriptor.offsets_m), bits(&b.descriptor.offsets_m));
            assert_eq!(a.descriptor.observed, b.descriptor.observed);
            assert_eq!(a.scan_stamps, b.scan_stamps);
            assert_eq!(a.contour_e1e2_m, b.contour_e1e2_m);
            assert_eq!(a.origin_in_submap, b.origin_in_submap);
            assert_eq!(a.strength.to_bits(), b.strength.to_bits());
        }
        let good = std::fs::read(&path).unwrap_or_default();
        let refused = |bytes: &[u8], needle: &str| {
            let p = dir.join("bad.park");
            assert!(std::fs::write(&p, bytes).is_ok());
            match read(&p) {
                Err(DecodError::Database { reason, .. }) => {
                    assert!(reason.contains(needle), "{reason} lacks {needle}")
                }
                other => panic!("expected a database error, got {other:?}"),
            }
        };
        refused(&good[..good.len() - 5], "landmark 2");
        let mut long_record = good.clone();
        long_record[20..28].copy_from_slice(&(good.len() as u64).to_le_bytes());
        refused(&long_record, "landmark 0");
        refused(b"DECODSVY\x01\x00\x00\x00", "DECODPRK");
        let mut huge = good.clone();
        huge[12..20].copy_from_slice(&u64::MAX.to_le_bytes());
        refused(&huge, "cannot fit");
        let mut longer = good.clone();
        longer.push(0);
        refused(&longer, "unexpected bytes");
        std::fs::remove_dir_all(&dir).ok();
    }
}
