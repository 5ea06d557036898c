//! TUM trajectory files: one pose per line, `stamp tx ty tz qx qy qz qw` (seconds, metres,
//! Hamilton quaternion); `#` comments and blank lines are skipped. The format every LIO
//! (FAST-LIO, KISS-ICP, ...) can export, and decod's own output format.

use std::io::Write;
use std::path::Path;

use crate::error::{DecodError, Result};
use crate::geometry::{Pose, pose_from_tq, pose_to_tq};

fn log_error(path: &Path, reason: String) -> DecodError {
    DecodError::Log {
        path: path.to_path_buf(),
        topic: None,
        reason,
    }
}

/// Reads a TUM file into `(stamp, T_world_body)` pairs, in file order. A malformed line is an
/// error naming the file and line number.
pub fn read_tum(path: &Path) -> Result<Vec<(f64, Pose)>> {
    let text = std::fs::read_to_string(path).map_err(|source| DecodError::Io {
        path: path.to_path_buf(),
        source,
    })?;
    let mut out = Vec::new();
    for (i, line) in text.lines().enumerate() {
        let line = line.trim();
        if line.is_empty() || line.starts_with('#') {
            continue;
        }
        let values: std::result::Result<Vec<f64>, _> =
            line.split_whitespace().map(str::parse::<f64>).collect();
        let v = values.map_err(|e| log_error(path, format!("line {}: {e}", i + 1)))?;
        if v.len() != 8 {
            return Err(log_error(
                path,
                format!(
                    "line {}: expected 8 values `stamp tx ty tz qx qy qz qw`, got {}",
                    i + 1,
                    v.len()
                ),
            ));
        }
        let pose = pose_from_tq([v[1], v[2], v[3]], [v[4], v[5], v[6], v[7]], "pose")
            .map_err(|e| log_error(path, format!("line {}: {e}", i + 1)))?;
        if !v[0].is_finite() {
            return Err(log_error(path, format!("line {}: non-finite stamp", i + 1)));
        }
        out.push((v[0], pose));
    }
    if out.is_empty() {
        return Err(log_error(path, "no poses in TUM file".into()));
    }
    Ok(out)
}

/// Writes `(stamp, T_world_body)` pairs as a TUM file (9 decimals on stamps, enough for ns).
pub fn write_tum(path: &Path, poses: &[(f64, Pose)]) -> Result<()> {
    let io_err = |source| DecodError::Io {
        path: path.to_path_buf(),
        source,
    };
    let mut out = std::io::BufWriter::new(std::fs::File::create(path).map_err(io_err)?);
    for (stamp, pose) in poses {
        let (t, q) = pose_to_tq(pose);
        writeln!(
            out,
            "{stamp:.9} {:.9} {:.9} {:.9} {:.9} {:.9} {:.9} {:.9}",
            t[0], t[1], t[2], q[0], q[1], q[2], q[3]
        )
        .map_err(io_err)?;
    }
    out.flush().map_err(io_err)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn round_trip_and_bad_lines() {
        let dir = std::env::temp_dir().join(format!("decod_tum_{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join("a.tum");
        let p = pose_from_tq([1.0, -2.0, 3.5], [0.0, 0.0, 0.6, 0.8], "p").unwrap();
        write_tum(&path, &[(12.5, p), (13.0, Pose::identity())]).unwrap();
        let back = read_tum(&path).unwrap();
        assert_eq!(back.len(), 2);
        assert!((back[0].1.to_homogeneous() - p.to_homogeneous()).norm() < 1e-8);
        std::fs::write(&path, "# c\n1 2 3\n").unwrap();
        let err = read_tum(&path).unwrap_err().to_string();
        assert!(err.contains("line 2") && err.contains("a.tum"), "{err}");
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
