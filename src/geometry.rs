//! Rigid-body helpers shared by ingestion (pose interpolation) and submaps (frame changes).
//! Poses are `Isometry3<f64>` named by their frames: `world_from_body` maps body-frame
//! points into the world (odometry) frame.

use nalgebra::{Isometry3, Matrix4, Quaternion, Translation3, UnitQuaternion, Vector3};

use crate::error::{DecodError, Result};

/// A rigid transform `T_target_source` (maps source-frame points to the target frame).
pub type Pose = Isometry3<f64>;

/// Pose from a translation and a quaternion `(x, y, z, w)`; the quaternion is normalised,
/// and a zero or non-finite one is an error naming `what`.
pub fn pose_from_tq(t: [f64; 3], q_xyzw: [f64; 4], what: &str) -> Result<Pose> {
    if t.iter().chain(q_xyzw.iter()).any(|v| !v.is_finite()) {
        return Err(DecodError::invalid(
            what,
            "non-finite translation or quaternion",
        ));
    }
    let q = Quaternion::new(q_xyzw[3], q_xyzw[0], q_xyzw[1], q_xyzw[2]);
    let norm = q.norm();
    if norm < 1e-9 {
        return Err(DecodError::invalid(what, "zero quaternion"));
    }
    Ok(Isometry3::from_parts(
        Translation3::new(t[0], t[1], t[2]),
        UnitQuaternion::from_quaternion(q),
    ))
}

/// Translation and quaternion `(x, y, z, w)` of a pose (TUM order).
pub fn pose_to_tq(pose: &Pose) -> ([f64; 3], [f64; 4]) {
    let t = pose.translation.vector;
    let q = pose.rotation.quaternion();
    ([t.x, t.y, t.z], [q.i, q.j, q.k, q.w])
}

/// Pose from a homogeneous 4x4 matrix (row-major); the rotation block must be orthonormal
/// within 1e-6 and the last row `[0 0 0 1]`.
pub fn pose_from_matrix(m: &[f64; 16], what: &str) -> Result<Pose> {
    if m.iter().any(|v| !v.is_finite()) {
        return Err(DecodError::invalid(what, "non-finite entries"));
    }
    let mat = Matrix4::from_row_slice(m);
    let last = mat.row(3);
    if (last[0].abs() + last[1].abs() + last[2].abs() + (last[3] - 1.0).abs()) > 1e-9 {
        return Err(DecodError::invalid(what, "last row must be [0, 0, 0, 1]"));
    }
    let r = mat.fixed_view::<3, 3>(0, 0).into_owned();
    let orth = (r.transpose() * r - nalgebra::Matrix3::identity()).norm();
    if orth > 1e-6 || r.determinant() < 0.0 {
        return Err(DecodError::invalid(
            what,
            format!("rotation block is not a proper rotation (|R^T R - I| = {orth:.2e})"),
        ));
    }
    let rot = nalgebra::Rotation3::from_matrix_unchecked(r);
    Ok(Isometry3::from_parts(
        Translation3::from(Vector3::new(mat[(0, 3)], mat[(1, 3)], mat[(2, 3)])),
        UnitQuaternion::from_rotation_matrix(&rot),
    ))
}

/// Row-major 4x4 matrix of a pose.
pub fn pose_to_matrix(pose: &Pose) -> [f64; 16] {
    let m = pose.to_homogeneous();
    let mut out = [0.0; 16];
    for r in 0..4 {
        for c in 0..4 {
            out[r * 4 + c] = m[(r, c)];
        }
    }
    out
}

/// SE(3) interpolation between `a` (at `s = 0`) and `b` (at `s = 1`): slerp on rotation,
/// linear on translation (the usual choice for odometry between two close stamps).
pub fn interpolate(a: &Pose, b: &Pose, s: f64) -> Pose {
    let t = a.translation.vector.lerp(&b.translation.vector, s);
    let q = a.rotation.slerp(&b.rotation, s);
    Isometry3::from_parts(Translation3::from(t), q)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn matrix_round_trip_and_interpolation_midpoint() {
        let a = pose_from_tq([1.0, 2.0, 3.0], [0.0, 0.0, 0.0, 1.0], "a").unwrap();
        let b = pose_from_tq(
            [3.0, 2.0, 3.0],
            [0.0, 0.0, (0.25f64).sin(), (0.25f64).cos()],
            "b",
        )
        .unwrap();
        let back = pose_from_matrix(&pose_to_matrix(&b), "m").unwrap();
        assert!((back.to_homogeneous() - b.to_homogeneous()).norm() < 1e-12);
        let mid = interpolate(&a, &b, 0.5);
        assert!((mid.translation.vector.x - 2.0).abs() < 1e-12);
        assert!((mid.rotation.angle() - 0.25).abs() < 1e-12);
    }

    #[test]
    fn bad_rotation_is_rejected() {
        let mut m = pose_to_matrix(&Pose::identity());
        m[0] = 2.0;
        assert!(pose_from_matrix(&m, "pose").is_err());
    }
}
