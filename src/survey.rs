//! A survey: what a later run needs to re-inspect the same corridor in this run's frame
//! (issue 12): the landmarks with their physical boundary (joint) ids, the corrected poses of
//! the submap anchors they are expressed in, the run's config and the decod version.
//!
//! **Format** (`survey.decod`, little-endian, no pickle, no code):
//!
//! ```text
//! magic      8 bytes  "DECODSVY"
//! version    u32      FORMAT_VERSION; any other is refused with both versions named
//! header     u64 n, then n bytes of UTF-8 JSON: {decod_version, config, anchors: [{stamp,
//!            pose (16, row-major world_from_anchor)}], joint_ids, landmarks (count), extra}
//! landmarks  `count` records: 17 f64 (stamp, origin, axis, e1, e2, radius, strength,
//!            cell_z_m, perimeter_m), 4 u32 (rows, cols, scans, contour points), the scan
//!            stamps (f64), the contour (2 f64 each), normal_e1 and normal_e2 (f64 x cols),
//!            the offsets (f32 x rows*cols: 0.1 µm steps at 1 m, far below the sensors'
//!            millimetres) and the observed mask (bits, rows*cols rounded up to bytes)
//! ```
//!
//! Every count is checked against [`MAX_CELLS`], [`MAX_SCANS`] and the bytes left in the file
//! before anything is allocated, so a corrupt or hostile file is an error naming the record,
//! never an allocation of its claimed size. Landmarks are validated ([`Landmark::validate`]).

use std::borrow::{Borrow, Cow};
use std::fs::File;
use std::io::{BufReader, BufWriter, Read, Write};
use std::path::{Path, PathBuf};
use std::sync::Arc;

use serde_json::Value;

use crate::error::{DecodError, Result};
use crate::landmark::{Descriptor, Landmark};
use crate::spill::{Held, Spill};

/// File magic.
pub const MAGIC: &[u8; 8] = b"DECODSVY";
/// Current format version; reading any other is an error.
pub const FORMAT_VERSION: u32 = 1;
/// Largest descriptor grid accepted (cells).
pub const MAX_CELLS: usize = 1 << 20;
/// Largest number of scans per submap accepted.
pub const MAX_SCANS: usize = 1 << 16;
/// Largest header accepted, bytes.
pub const MAX_HEADER_BYTES: u64 = 1 << 30;
/// The smallest landmark record: 17 f64 and 4 u32 (bounds a file's claimed count).
pub(crate) const MIN_RECORD_BYTES: u64 = 17 * 8 + 16;

/// A survey in memory: the JSON header (see the module docs) and the landmarks.
#[derive(Clone, Debug)]
pub struct Survey {
    /// Header object: `decod_version`, `config`, `anchors`, `joint_ids`, anything else.
    pub header: Value,
    /// The landmarks, in the order of `header.joint_ids`.
    pub landmarks: Vec<Landmark>,
}

pub(crate) fn err(path: &Path, reason: impl Into<String>) -> DecodError {
    DecodError::Database {
        path: path.to_path_buf(),
        reason: reason.into(),
    }
}

fn put_f64s(out: &mut Vec<u8>, values: &[f64]) {
    for v in values {
        out.extend_from_slice(&v.to_le_bytes());
    }
}

fn put_u32(out: &mut Vec<u8>, value: usize, path: &Path) -> Result<()> {
    let v = u32::try_from(value).map_err(|_| err(path, format!("count {value} too large")))?;
    out.extend_from_slice(&v.to_le_bytes());
    Ok(())
}

pub(crate) fn encode_landmark(out: &mut Vec<u8>, l: &Landmark, path: &Path) -> Result<()> {
    let d = &l.descriptor;
    let mut fixed = vec![l.submap_stamp];
    for v in [
        &l.origin_in_submap,
        &l.axis_in_submap,
        &l.e1_in_submap,
        &l.e2_in_submap,
    ] {
        fixed.extend_from_slice(v);
    }
    fixed.extend_from_slice(&[l.radius_m, l.strength, d.cell_z_m, d.perimeter_m]);
    put_f64s(out, &fixed);
    for n in [d.rows, d.cols, l.scan_stamps.len(), l.contour_e1e2_m.len()] {
        put_u32(out, n, path)?;
    }
    put_f64s(out, &l.scan_stamps);
    for p in &l.contour_e1e2_m {
        put_f64s(out, p);
    }
    put_f64s(out, &d.normal_e1);
    put_f64s(out, &d.normal_e2);
    for v in &d.offsets_m {
        out.extend_from_slice(&v.to_le_bytes());
    }
    let mut bits = vec![0u8; d.observed.len().div_ceil(8)];
    for (i, _) in d.observed.iter().enumerate().filter(|(_, o)| **o) {
        bits[i / 8] |= 1 << (i % 8);
    }
    out.extend_from_slice(&bits);
    Ok(())
}

/// The file beside `path` a survey is written into before it is renamed to `path`.
fn partial_path(path: &Path) -> PathBuf {
    let mut name = path.file_name().unwrap_or_default().to_os_string();
    name.push(".partial");
    path.with_file_name(name)
}

/// Writes a survey of `header` and `landmarks` (module docs) without copying them
/// ([`write_records`]). `header` must be a JSON object whose `joint_ids` hold one id per
/// landmark. A run's write stage held a copy of every landmark and the whole file in memory
/// (0.35 GB of a 400 m pipe's 5,376 landmarks, the run's peak: `docs/measurements.md`, "Long
/// logs").
pub fn write_survey<L: Source>(path: &Path, header: &Value, landmarks: &[L]) -> Result<()> {
    let ids = header.get("joint_ids").and_then(Value::as_array);
    if ids.map(Vec::len) != Some(landmarks.len()) {
        return Err(err(path, "header.joint_ids must hold one id per landmark"));
    }
    let mut header = header.clone();
    if let Some(obj) = header.as_object_mut() {
        obj.insert("landmarks".into(), Value::from(landmarks.len()));
    } else {
        return Err(err(path, "header must be a JSON object"));
    }
    let text = serde_json::to_vec(&header).map_err(|e| err(path, e.to_string()))?;
    let mut head = Vec::with_capacity(text.len() + 64);
    head.extend_from_slice(MAGIC);
    head.extend_from_slice(&FORMAT_VERSION.to_le_bytes());
    head.extend_from_slice(&(text.len() as u64).to_le_bytes());
    head.extend_from_slice(&text);
    write_records(path, &head, landmarks, false)
}

/// A landmark a file's writer takes: one in memory, or one whose cells wait in a run's spill
/// ([`Held`], read back when its record is written).
pub trait Source {
    /// The landmark: borrowed where it is in memory, read back where it is not.
    fn landmark(&self) -> Result<Cow<'_, Landmark>>;
    /// Whether it is read back (validated then, as when it was set aside).
    fn on_disk(&self) -> bool;
}

impl<L: Borrow<Landmark>> Source for L {
    fn landmark(&self) -> Result<Cow<'_, Landmark>> {
        Ok(Cow::Borrowed(self.borrow()))
    }
    fn on_disk(&self) -> bool {
        false
    }
}

impl Source for Held {
    fn landmark(&self) -> Result<Cow<'_, Landmark>> {
        match self {
            Held::Memory(l) => Ok(Cow::Borrowed(l)),
            Held::Disk(_) => Ok(Cow::Owned(Arc::unwrap_or_clone(Held::landmark(self)?))),
        }
    }
    fn on_disk(&self) -> bool {
        Held::on_disk(self)
    }
}

/// Writes `head`, then one record per landmark (those in memory validated first: one that
/// fails is refused before a byte is written; those in a spill were validated when they went
/// there and are again when read back), each encoded into one reused buffer and streamed to
/// the file, which appears under `path` only once complete (written beside it, then
/// renamed). `framed`: each record preceded by its length in bytes (u64), so that a reader
/// can take them one at a time.
pub(crate) fn write_records<L: Source>(
    path: &Path,
    head: &[u8],
    landmarks: &[L],
    framed: bool,
) -> Result<()> {
    for l in landmarks.iter().filter(|l| !l.on_disk()) {
        l.landmark()?.validate()?;
    }
    let partial = partial_path(path);
    let io = |source| DecodError::Io {
        path: path.to_path_buf(),
        source,
    };
    let written = (|| -> Result<()> {
        let mut file = BufWriter::new(File::create(&partial).map_err(io)?);
        file.write_all(head).map_err(io)?;
        let mut out = Vec::new();
        for l in landmarks {
            out.clear();
            encode_landmark(&mut out, &*l.landmark()?, path)?;
            if framed {
                file.write_all(&(out.len() as u64).to_le_bytes())
                    .map_err(io)?;
            }
            file.write_all(&out).map_err(io)?;
        }
        file.into_inner().map_err(|e| io(e.into_error()))?;
        std::fs::rename(&partial, path).map_err(io)
    })();
    if written.is_err() {
        std::fs::remove_file(&partial).ok();
    }
    written
}

impl Survey {
    /// Writes the survey (module docs; [`write_survey`]). `header` must be a JSON object;
    /// `joint_ids` in it must hold one id per landmark.
    pub fn write(&self, path: &Path) -> Result<()> {
        write_survey(path, &self.header, &self.landmarks)
    }

    /// Reads a survey written by [`Self::write`]; another format version, a foreign file or
    /// a truncated or inconsistent one is a [`DecodError::Database`] saying which.
    pub fn read(path: &Path) -> Result<Self> {
        let (header, landmarks) = read_records(path, |l, _| Ok(l))?;
        Ok(Self { header, landmarks })
    }

    /// [`Self::read`] with each landmark put into `spill` as soon as it is read
    /// ([`Spill::put`]): the survey's landmarks then hold their heads in memory, not their
    /// cells (a re-inspection's survey is a whole earlier run's landmarks, 29 KB each).
    pub fn read_into(path: &Path, spill: &Arc<Spill>) -> Result<(Value, Vec<Held>)> {
        read_records(path, |l, record| spill.put_record(&l, record))
    }
}

/// Reads the survey at `path` (module docs): checks its magic, version, header and sizes
/// (the landmark count bounded by the file's size before anything is allocated for it) and
/// hands each landmark, validated, to `each` with its record's bytes, in order. The header
/// and what `each` made.
/// The file is read a record at a time (a record's length follows from the counts at its
/// start), so a survey put into a spill never has its whole file in memory.
fn read_records<T>(
    path: &Path,
    mut each: impl FnMut(Landmark, &[u8]) -> Result<T>,
) -> Result<(Value, Vec<T>)> {
    let io = |source| DecodError::Io {
        path: path.to_path_buf(),
        source,
    };
    let file = File::open(path).map_err(io)?;
    let size = file.metadata().map_err(io)?.len();
    let mut input = Records {
        file: BufReader::new(file),
        left: size,
        path,
    };
    let header = read_header(&mut input)?;
    let n = header
        .get("landmarks")
        .and_then(Value::as_u64)
        .ok_or_else(|| err(path, "header has no landmark count"))?;
    let ids = header.get("joint_ids").and_then(Value::as_array);
    if ids.map(|a| a.len() as u64) != Some(n) {
        return Err(err(
            path,
            "header.joint_ids does not hold one id per landmark",
        ));
    }
    // Bound the count by the bytes left before allocating for it.
    if n > input.left / MIN_RECORD_BYTES {
        return Err(err(path, format!("{n} landmarks cannot fit in the file")));
    }
    let mut out = Vec::with_capacity(n as usize);
    for k in 0..n as usize {
        let (l, record) = input
            .landmark()
            .and_then(|(l, record)| l.validate().map(|()| (l, record)))
            .map_err(|e| err(path, format!("landmark {k}: {e}")))?;
        out.push(each(l, &record)?);
    }
    if input.left != 0 {
        return Err(err(
            path,
            format!("{} unexpected bytes at the end", input.left),
        ));
    }
    Ok((header, out))
}

/// A survey file read in order, with the bytes it has left.
struct Records<'a, R> {
    file: R,
    left: u64,
    path: &'a Path,
}

impl<R: Read> Records<'_, R> {
    /// The next `n` bytes (`n` checked against the bytes left first).
    fn take(&mut self, n: u64) -> Result<Vec<u8>> {
        if n > self.left {
            return Err(err(
                self.path,
                format!("truncated: {n} bytes needed, {} left", self.left),
            ));
        }
        let mut buf = vec![0u8; n as usize];
        self.file
            .read_exact(&mut buf)
            .map_err(|source| DecodError::Io {
                path: self.path.to_path_buf(),
                source,
            })?;
        self.left -= n;
        Ok(buf)
    }

    /// The next landmark and its record: the fixed part, whose counts give the rest's length.
    fn landmark(&mut self) -> Result<(Landmark, Vec<u8>)> {
        let mut record = self.take(MIN_RECORD_BYTES)?;
        let rest = Reader::new(&record, self.path).rest_of_record()?;
        record.extend(self.take(rest)?);
        let mut r = Reader::new(&record, self.path);
        let landmark = r.landmark()?;
        match r.left() {
            0 => Ok((landmark, record)),
            n => Err(err(self.path, format!("{n} bytes of a record left unread"))),
        }
    }
}

/// The magic, the format version and the JSON header at the start of a survey.
fn read_header<R: Read>(input: &mut Records<'_, R>) -> Result<Value> {
    const PREFIX: u64 = 8 + 4 + 8;
    let path = input.path;
    if input.left < PREFIX {
        return Err(err(path, "not a decod survey (no DECODSVY magic)"));
    }
    let prefix = input.take(PREFIX)?;
    let mut r = Reader::new(&prefix, path);
    if r.take(8).ok() != Some(&MAGIC[..]) {
        return Err(err(path, "not a decod survey (no DECODSVY magic)"));
    }
    let version = r.u32()?;
    if version != FORMAT_VERSION {
        return Err(err(
            path,
            format!(
                "survey format version {version} is not supported: this decod ({}) reads \
                 version {FORMAT_VERSION}; re-run the survey with this version",
                env!("CARGO_PKG_VERSION")
            ),
        ));
    }
    let n = r.u64()?;
    if n > MAX_HEADER_BYTES {
        return Err(err(path, format!("header of {n} bytes is implausible")));
    }
    serde_json::from_slice(&input.take(n)?).map_err(|e| err(path, format!("corrupt header: {e}")))
}

/// A bounds-checked little-endian cursor.
pub(crate) struct Reader<'a> {
    bytes: &'a [u8],
    at: usize,
    path: PathBuf,
}

impl<'a> Reader<'a> {
    /// A cursor at the start of `bytes`, read from `path` (named in its errors).
    pub(crate) fn new(bytes: &'a [u8], path: &Path) -> Self {
        Self {
            bytes,
            at: 0,
            path: path.to_path_buf(),
        }
    }

    pub(crate) fn left(&self) -> usize {
        self.bytes.len() - self.at
    }

    pub(crate) fn take(&mut self, n: usize) -> Result<&'a [u8]> {
        if n > self.left() {
            return Err(err(
                &self.path,
                format!("truncated: {n} bytes needed at offset {}", self.at),
            ));
        }
        let out = &self.bytes[self.at..self.at + n];
        self.at += n;
        Ok(out)
    }

    fn array<const N: usize>(&mut self) -> Result<[u8; N]> {
        let mut a = [0u8; N];
        a.copy_from_slice(self.take(N)?);
        Ok(a)
    }

    pub(crate) fn u32(&mut self) -> Result<u32> {
        Ok(u32::from_le_bytes(self.array()?))
    }

    pub(crate) fn u64(&mut self) -> Result<u64> {
        Ok(u64::from_le_bytes(self.array()?))
    }

    /// `n` f64 after checking that they are in the file.
    fn f64s(&mut self, n: usize) -> Result<Vec<f64>> {
        let raw = self.take(n.saturating_mul(8))?;
        Ok(raw
            .chunks_exact(8)
            .map(|c| f64::from_le_bytes([c[0], c[1], c[2], c[3], c[4], c[5], c[6], c[7]]))
            .collect())
    }

    /// A record's counts (rows, cols, scans, contour points), read after its 17 f64 and
    /// checked against the format's bounds.
    fn counts(&mut self) -> Result<(usize, usize, usize, usize)> {
        let (rows, cols) = (self.u32()? as usize, self.u32()? as usize);
        let (scans, contour) = (self.u32()? as usize, self.u32()? as usize);
        let cells = rows.saturating_mul(cols);
        if cells == 0 || cells > MAX_CELLS || scans > MAX_SCANS || contour > MAX_CELLS {
            return Err(DecodError::invalid(
                "survey record",
                format!(
                    "implausible sizes: grid {rows} x {cols}, {scans} scans, {contour} contour"
                ),
            ));
        }
        Ok((rows, cols, scans, contour))
    }

    /// How many bytes of a record follow its fixed part ([`MIN_RECORD_BYTES`], which this
    /// reader holds): the scan stamps, the contour, the normals, the offsets and the mask,
    /// as [`Self::landmark`] reads them.
    fn rest_of_record(&mut self) -> Result<u64> {
        self.take(17 * 8)?;
        let (rows, cols, scans, contour) = self.counts()?;
        let cells = rows * cols;
        Ok((8 * scans + 16 * contour + 16 * cols + 4 * cells + cells.div_ceil(8)) as u64)
    }

    pub(crate) fn landmark(&mut self) -> Result<Landmark> {
        let f = self.f64s(17)?;
        let v3 = |i: usize| [f[i], f[i + 1], f[i + 2]];
        let (rows, cols, scans, contour) = self.counts()?;
        let cells = rows * cols;
        let scan_stamps = self.f64s(scans)?;
        let points = self.f64s(2 * contour)?;
        let normal_e1 = self.f64s(cols)?;
        let normal_e2 = self.f64s(cols)?;
        let offsets_m = self
            .take(4 * cells)?
            .chunks_exact(4)
            .map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]]))
            .collect();
        let bits = self.take(cells.div_ceil(8))?;
        let observed = (0..cells)
            .map(|i| bits[i / 8] & (1 << (i % 8)) != 0)
            .collect();
        Ok(Landmark {
            submap_stamp: f[0],
            scan_stamps,
            origin_in_submap: v3(1),
            axis_in_submap: v3(4),
            e1_in_submap: v3(7),
            e2_in_submap: v3(10),
            contour_e1e2_m: points.chunks_exact(2).map(|p| [p[0], p[1]]).collect(),
            radius_m: f[13],
            strength: f[14],
            descriptor: Descriptor {
                rows,
                cols,
                cell_z_m: f[15],
                perimeter_m: f[16],
                offsets_m,
                observed,
                normal_e1,
                normal_e2,
            },
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::matching::synthetic::{Grid, JointSurface, Observation, Rng, SurfaceParams};

    fn landmarks(n: usize) -> Vec<Landmark> {
        let g = Grid::pipe();
        let mut rng = Rng::new(5);
        (0..n as u64)
            .map(|k| {
                JointSurface::new(g, SurfaceParams::for_grid(&g), 1, k)
                    .observe(&Observation::random(&g, k as f64, false, &mut rng), k)
            })
            .collect()
    }

    fn survey(n: usize) -> Survey {
        Survey {
            header: serde_json::json!({"decod_version": "test", "joint_ids": (0..n).collect::<Vec<_>>()}),
            landmarks: landmarks(n),
        }
    }

    #[test]
    fn round_trip_keeps_every_field() {
        let dir = std::env::temp_dir().join(format!("decod-survey-{}", std::process::id()));
        std::fs::create_dir_all(&dir).ok();
        let path = dir.join("rt.decod");
        let s = survey(3);
        assert!(s.write(&path).is_ok());
        let back = Survey::read(&path).expect("reads back");
        assert_eq!(back.landmarks.len(), 3);
        // Exact: a record holds what a landmark holds (the offsets in f32 in both).
        assert_eq!(s.landmarks, back.landmarks);
        assert_eq!(back.header["landmarks"], 3);
        // Read into a spill: the same header, each landmark on disk and the same when read
        // back; a corrupt file is refused the same way.
        let spill = Spill::create(&dir).expect("spill");
        let (header, held) = Survey::read_into(&path, &spill).expect("reads into the spill");
        assert_eq!(header, back.header);
        assert!(held.iter().all(Held::on_disk));
        let again: Vec<Landmark> = held
            .iter()
            .map(|h| Landmark::clone(&h.landmark().expect("reads back")))
            .collect();
        assert_eq!(again, s.landmarks);
        let bytes = std::fs::read(&path).expect("survey bytes");
        std::fs::write(&path, &bytes[..bytes.len() - 5]).expect("cut");
        assert!(Survey::read_into(&path, &spill).is_err());
        std::fs::remove_dir_all(&dir).ok();
    }

    #[test]
    fn shared_landmarks_are_written_whole_or_not_at_all() {
        let dir = std::env::temp_dir().join(format!("decod-survey-arc-{}", std::process::id()));
        std::fs::create_dir_all(&dir).ok();
        let (path, partial) = (dir.join("s.decod"), dir.join("s.decod.partial"));
        let s = survey(3);
        let shared: Vec<std::sync::Arc<Landmark>> = s
            .landmarks
            .iter()
            .cloned()
            .map(std::sync::Arc::new)
            .collect();
        assert!(write_survey(&path, &s.header, &shared).is_ok());
        assert!(!partial.exists());
        let back = Survey::read(&path).expect("reads back");
        assert_eq!(back.landmarks.len(), 3);
        assert_eq!(back.landmarks[2].scan_stamps, s.landmarks[2].scan_stamps);
        // A landmark that fails validation: refused before anything is written, and the
        // survey already there is left as it was.
        let before = std::fs::read(&path).unwrap_or_default();
        let mut bad = s.landmarks.clone();
        bad[1].descriptor.offsets_m.pop();
        assert!(write_survey(&path, &s.header, &bad).is_err());
        assert_eq!(std::fs::read(&path).unwrap_or_default(), before);
        assert!(!partial.exists());
        std::fs::remove_dir_all(&dir).ok();
    }

    #[test]
    fn other_versions_truncation_and_huge_counts_are_refused() {
        let dir = std::env::temp_dir().join(format!("decod-survey-bad-{}", std::process::id()));
        std::fs::create_dir_all(&dir).ok();
        let path = dir.join("s.decod");
        assert!(survey(2).write(&path).is_ok());
        let good = std::fs::read(&path).unwrap_or_default();
        let check = |bytes: &[u8], needle: &str| {
            let p = dir.join("bad.decod");
            assert!(std::fs::write(&p, bytes).is_ok());
            match Survey::read(&p) {
                Err(DecodError::Database { reason, .. }) => {
                    assert!(reason.contains(needle), "{reason} lacks {needle}")
                }
                other => panic!("expected a database error, got {other:?}"),
            }
        };
        let mut v2 = good.clone();
        v2[8..12].copy_from_slice(&2u32.to_le_bytes());
        check(&v2, "version 2 is not supported");
        check(&good[..good.len() - 10], "truncated");
        check(b"PK\x03\x04 something else", "not a decod survey");
        // A record claiming a 2^31-cell grid is refused before any allocation.
        let header_len = u64::from_le_bytes(good[12..20].try_into().unwrap_or([0; 8])) as usize;
        let mut huge = good.clone();
        let rows_at = 20 + header_len + 17 * 8;
        huge[rows_at..rows_at + 4].copy_from_slice(&65_536u32.to_le_bytes());
        huge[rows_at + 4..rows_at + 8].copy_from_slice(&32_768u32.to_le_bytes());
        check(&huge, "implausible sizes");
        // Read a record at a time: every cut is refused, a byte more too.
        for cut in (0..good.len()).step_by(97).chain([good.len() - 1]) {
            let p = dir.join("cut.decod");
            assert!(std::fs::write(&p, &good[..cut]).is_ok());
            assert!(Survey::read(&p).is_err(), "cut at {cut}");
        }
        check(
            &[&good[..], &[0u8]].concat(),
            "1 unexpected bytes at the end",
        );
        std::fs::remove_dir_all(&dir).ok();
    }
}
