//! A run's landmarks on disk once extracted (beyond the paper; DESIGN.md asks for memory
//! bounded by the submap, not by the log).
//!
//! A landmark's cells (the offsets, the observed mask, the normals and the contour: about
//! 28 of its 29 KB) are needed twice in a run: when the matcher prepares its view, and when
//! the survey is written. In between a long log's landmarks were held in memory, the larger
//! part of what grew with the log (400 m of pipe: 5,376 landmarks, 0.16 GB;
//! `docs/measurements.md`, "Long logs"). A [`Spill`] keeps them in one file instead, written
//! as they are extracted; a [`Held`] landmark is then its fields without the cells (its
//! *head*, a few hundred bytes) and where its record lies, read back exactly (the survey's
//! record, `crate::survey`: the offsets in f32 as a landmark holds them) each time the cells
//! are asked for, by one positioned read that leaves the file's other readers alone. The
//! matcher's views put their patches in the same file while the passes are matched
//! ([`Record`], `crate::matching::PreparedLandmark::set_aside`).
//!
//! **The file** is the run's own and holds no code: a record is written by this process and
//! read back only by it, its length and place kept in memory, every landmark validated when
//! it is read as when it was written and a view's patches checked against their sizes. On
//! Unix it is unlinked as soon as it is created, so it takes no name and goes when the last
//! landmark or view that points into it does, whatever way the run ends; elsewhere it is
//! removed when the [`Spill`] is dropped.

use std::fs::{File, OpenOptions};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};

use crate::error::{DecodError, Result};
use crate::landmark::Landmark;
use crate::survey::{Reader, encode_landmark, err};

/// Files created by this process so far (their names must differ).
static CREATED: AtomicU64 = AtomicU64::new(0);

/// The file a run's landmarks are written to (module docs).
#[derive(Debug)]
pub struct Spill {
    file: File,
    /// Where the file was created (named in errors; removed on drop where it was not
    /// unlinked at creation).
    path: PathBuf,
    unlinked: bool,
    /// Bytes written so far; appends hold the lock.
    end: Mutex<u64>,
}

/// Where a record lies in its [`Spill`] (the spill lives as long as its records).
#[derive(Clone, Debug)]
pub struct Record {
    spill: Arc<Spill>,
    at: u64,
    len: usize,
}

/// A landmark's record in its [`Spill`], with the landmark's head.
#[derive(Debug)]
pub struct OnDisk {
    head: Arc<Landmark>,
    record: Record,
}

/// A landmark in memory, or its head with its record in a [`Spill`] (module docs).
#[derive(Clone, Debug)]
pub enum Held {
    /// The whole landmark in memory.
    Memory(Arc<Landmark>),
    /// The cells on disk.
    Disk(Arc<OnDisk>),
}

impl Spill {
    /// A new, empty file in `dir` (module docs).
    pub fn create(dir: &Path) -> Result<Arc<Self>> {
        let n = CREATED.fetch_add(1, Ordering::Relaxed);
        let path = dir.join(format!(".decod-landmarks-{}-{n}.spill", std::process::id()));
        let io = |source| DecodError::Io {
            path: path.clone(),
            source,
        };
        let file = OpenOptions::new()
            .read(true)
            .write(true)
            .create_new(true)
            .open(&path)
            .map_err(io)?;
        let unlinked = cfg!(unix) && std::fs::remove_file(&path).is_ok();
        Ok(Arc::new(Self {
            file,
            path,
            unlinked,
            end: Mutex::new(0),
        }))
    }

    /// Bytes written so far.
    pub fn bytes(&self) -> u64 {
        self.end.lock().map_or(0, |end| *end)
    }

    /// Writes `landmark`'s record (validated first) at the end of the file; the landmark as
    /// [`Held::Disk`].
    pub fn put(self: &Arc<Self>, landmark: &Landmark) -> Result<Held> {
        landmark.validate()?;
        let mut bytes = Vec::new();
        encode_landmark(&mut bytes, landmark, &self.path)?;
        self.put_record(landmark, &bytes)
    }

    /// [`Self::put`] for a landmark already validated whose record is `record` (a survey's,
    /// read from its file: the same format), written as it is.
    pub(crate) fn put_record(self: &Arc<Self>, landmark: &Landmark, record: &[u8]) -> Result<Held> {
        Ok(Held::Disk(Arc::new(OnDisk {
            head: Arc::new(landmark.head()),
            record: self.append(record)?,
        })))
    }

    /// Writes `bytes` at the end of the file.
    pub(crate) fn append(self: &Arc<Self>, bytes: &[u8]) -> Result<Record> {
        let mut end = self
            .end
            .lock()
            .map_err(|_| err(&self.path, "a writer panicked"))?;
        let at = *end;
        write_all_at(&self.file, bytes, at).map_err(|source| DecodError::Io {
            path: self.path.clone(),
            source,
        })?;
        *end += bytes.len() as u64;
        Ok(Record {
            spill: Arc::clone(self),
            at,
            len: bytes.len(),
        })
    }
}

impl Record {
    /// The record's bytes, read back.
    pub(crate) fn bytes(&self) -> Result<Vec<u8>> {
        let mut buf = vec![0u8; self.len];
        read_exact_at(&self.spill.file, &mut buf, self.at).map_err(|source| DecodError::Io {
            path: self.spill.path.clone(),
            source,
        })?;
        Ok(buf)
    }

    /// The file it lies in (named in errors).
    pub(crate) fn path(&self) -> &Path {
        &self.spill.path
    }

    /// The landmark the record holds, read and validated.
    fn landmark(&self) -> Result<Landmark> {
        let buf = self.bytes()?;
        let mut r = Reader::new(&buf, self.path());
        let landmark = r.landmark()?;
        if r.left() != 0 {
            return Err(err(
                self.path(),
                format!("{} bytes beyond the record at {}", r.left(), self.at),
            ));
        }
        landmark.validate()?;
        Ok(landmark)
    }
}

impl Drop for Spill {
    fn drop(&mut self) {
        if !self.unlinked {
            std::fs::remove_file(&self.path).ok();
        }
    }
}

// Positioned reads and writes: neither moves a cursor another thread relies on.
#[cfg(unix)]
fn read_exact_at(file: &File, buf: &mut [u8], at: u64) -> std::io::Result<()> {
    std::os::unix::fs::FileExt::read_exact_at(file, buf, at)
}

#[cfg(unix)]
fn write_all_at(file: &File, buf: &[u8], at: u64) -> std::io::Result<()> {
    std::os::unix::fs::FileExt::write_all_at(file, buf, at)
}

#[cfg(windows)]
fn write_all_at(file: &File, mut buf: &[u8], mut at: u64) -> std::io::Result<()> {
    use std::os::windows::fs::FileExt;
    while !buf.is_empty() {
        match file.seek_write(buf, at)? {
            0 => return Err(std::io::ErrorKind::WriteZero.into()),
            n => {
                buf = &buf[n..];
                at += n as u64;
            }
        }
    }
    Ok(())
}

#[cfg(windows)]
fn read_exact_at(file: &File, mut buf: &mut [u8], mut at: u64) -> std::io::Result<()> {
    use std::os::windows::fs::FileExt;
    while !buf.is_empty() {
        match file.seek_read(buf, at)? {
            0 => return Err(std::io::ErrorKind::UnexpectedEof.into()),
            n => {
                buf = &mut buf[n..];
                at += n as u64;
            }
        }
    }
    Ok(())
}

impl Held {
    /// The landmark's fields; **its cells are empty when it is on disk** (module docs): what
    /// needs them asks [`Self::landmark`].
    pub fn head(&self) -> &Landmark {
        match self {
            Self::Memory(l) => l,
            Self::Disk(d) => &d.head,
        }
    }

    /// The whole landmark: itself in memory, else read back from its spill.
    pub fn landmark(&self) -> Result<Arc<Landmark>> {
        match self {
            Self::Memory(l) => Ok(Arc::clone(l)),
            Self::Disk(d) => d.record.landmark().map(Arc::new),
        }
    }

    /// The landmark's head ([`Landmark::head`]): shared where it is on disk, stripped from
    /// it where it is in memory.
    pub fn stripped(&self) -> Arc<Landmark> {
        match self {
            Self::Memory(l) => Arc::new(l.head()),
            Self::Disk(d) => Arc::clone(&d.head),
        }
    }

    /// Whether the cells are on disk.
    pub fn on_disk(&self) -> bool {
        matches!(self, Self::Disk(_))
    }
}

impl From<Arc<Landmark>> for Held {
    fn from(l: Arc<Landmark>) -> Self {
        Self::Memory(l)
    }
}

impl From<Landmark> for Held {
    fn from(l: Landmark) -> Self {
        Self::Memory(Arc::new(l))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::matching::synthetic::{Grid, JointSurface, Observation, Rng, SurfaceParams};

    fn landmarks(n: u64) -> Vec<Landmark> {
        let g = Grid::tunnel();
        let mut rng = Rng::new(5);
        (0..n)
            .map(|k| {
                JointSurface::new(g, SurfaceParams::for_grid(&g), 1, k)
                    .observe(&Observation::random(&g, k as f64, false, &mut rng), k)
            })
            .collect()
    }

    fn same(a: &Landmark, b: &Landmark) {
        let bits = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
        assert_eq!(bits(&a.descriptor.offsets_m), bits(&b.descriptor.offsets_m));
        assert_eq!(a, b);
    }

    #[test]
    fn landmarks_come_back_exactly_from_many_readers_and_leave_no_file() {
        let dir = std::env::temp_dir().join(format!("decod-spill-{}", std::process::id()));
        std::fs::create_dir_all(&dir).ok();
        let originals = landmarks(6);
        let held: Vec<Held> = {
            let Ok(spill) = Spill::create(&dir) else {
                panic!("cannot create a spill in {dir:?}")
            };
            let held: Vec<Held> = originals
                .iter()
                .map(|l| spill.put(l).unwrap_or_else(|e| panic!("{e}")))
                .collect();
            assert!(spill.bytes() > 6 * 16 * 256 * 4);
            held
        };
        // Unlinked at once on Unix: the directory holds nothing while the landmarks live.
        if cfg!(unix) {
            assert_eq!(std::fs::read_dir(&dir).map(|d| d.count()).unwrap_or(1), 0);
        }
        for (h, l) in held.iter().zip(&originals) {
            assert!(h.on_disk());
            assert!(h.head().descriptor.offsets_m.is_empty());
            assert!(h.head().validate().is_err());
            assert_eq!(h.head().origin_in_submap, l.origin_in_submap);
            assert_eq!(h.head().scan_stamps, l.scan_stamps);
        }
        // Read back in parallel, in any order, as often as asked.
        std::thread::scope(|s| {
            for t in 0..4 {
                let (held, originals) = (&held, &originals);
                s.spawn(move || {
                    for k in (0..held.len()).rev().chain(0..held.len()) {
                        let k = (k + t) % held.len();
                        same(
                            &held[k].landmark().unwrap_or_else(|e| panic!("{e}")),
                            &originals[k],
                        );
                    }
                });
            }
        });
        drop(held);
        if !cfg!(unix) {
            assert_eq!(std::fs::read_dir(&dir).map(|d| d.count()).unwrap_or(1), 0);
        }
        std::fs::remove_dir_all(&dir).ok();
    }

    #[test]
    fn an_invalid_landmark_is_refused_before_a_byte_is_written_and_a_bad_directory_is_named() {
        let dir = std::env::temp_dir().join(format!("decod-spill-bad-{}", std::process::id()));
        std::fs::create_dir_all(&dir).ok();
        let Ok(spill) = Spill::create(&dir) else {
            panic!("cannot create a spill in {dir:?}")
        };
        let mut bad = landmarks(1).remove(0);
        bad.descriptor.offsets_m.pop();
        assert!(matches!(
            spill.put(&bad),
            Err(DecodError::InvalidInput { .. })
        ));
        assert!(spill.put(&bad.head()).is_err());
        assert_eq!(spill.bytes(), 0);
        let missing = dir.join("no-such-directory");
        match Spill::create(&missing) {
            Err(DecodError::Io { path, .. }) => assert!(path.starts_with(&missing)),
            other => panic!("expected an I/O error naming the file, got {other:?}"),
        }
        std::fs::remove_dir_all(&dir).ok();
    }
}
