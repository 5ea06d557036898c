//! The 5-DoF landmark factor's residual and Jacobians (paper §III-C, Eq. `residual`),
//! evaluated for the Python pose graph (`python/decod_rs/landmark_factor.py` wraps it in a
//! `gtsam.CustomFactor`; GTSAM calls it once per factor and linearisation, tens of thousands
//! of times per run: 25 us in numpy, a few here).
//!
//! For a verified boundary pair, query landmark `i` observed from pose `T_i` and database
//! landmark `j` observed from `T_j` (both `world_from_body`): `c_i`, `a_i` the boundary
//! origin (metres) and unit corridor axis in the body frame of `T_i`, `c_j`, `a_j` in that of
//! `T_j`, and `T_ij = T_i^-1 T_j = (R_ij, t_ij)`. Our reading of the paper's
//! `r_ij = t_ij - (c̄_i - c̄_j)` with "these vectors expressed in frame k_i under the current
//! relative pose" (`c̄_j = R_ij c_j`):
//!
//! `r = T_ij * c_j - c_i` (3, metres, frame `k_i`): the two origins coincide in the world;
//! `delta = 1 - (a_i' R_ij a_j)^2`: the axes are parallel, in either direction (a reversed
//! traversal flips an axis, which `delta` ignores). Rotating either pose about the shared
//! axis through the landmark origin changes neither term: the roll about the degenerate axis
//! stays free, the point of the factor (§III-C, §IV-D). `delta = sin^2 theta` for an axis
//! misalignment `theta`, so `landmark_axis_sigma = 0.01` reads "about 0.1 rad is one sigma".
//!
//! Jacobians are analytic, for GTSAM's Pose3 chart: right-multiplied tangent perturbations
//! `xi = [w, v]` (rotation first), `R -> R Exp(w)`, `t -> t + R v`. With `q = T_ij c_j`,
//! `b = R_ij a_j` and `s = a_i' b`:
//!
//! ```text
//! dr/dw_i = [q]x          dr/dv_i = -I
//! dr/dw_j = -R_ij [c_j]x  dr/dv_j = R_ij
//! ddelta/dw_i = -2 s a_i' [b]x      ddelta/dw_j = 2 s a_i' R_ij [a_j]x
//! ddelta/dv_i = ddelta/dv_j = 0
//! ```
//!
//! checked against central finite differences through `gtsam.Pose3.retract` in
//! `tests/test_graph.py`. A `frame` rotation is applied to the position rows (residual and
//! Jacobians) so that the noise model's sigmas are along the corridor and across it.

use nalgebra::{Matrix3, Matrix4, SMatrix, Vector3, Vector4};

/// Residual rows: 3 position components (metres, frame `k_i`), then the axis term.
pub const RESIDUAL_DIM: usize = 4;

/// A (4, 6) Jacobian with respect to one pose's tangent space `[w, v]`.
pub type Jacobian = SMatrix<f64, RESIDUAL_DIM, 6>;

/// One boundary pair as the factor sees it: origins and unit axes in their own body frames,
/// and the rotation applied to the position rows.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct LandmarkPair {
    /// Query origin `c_i`, body frame of `T_i`, metres.
    pub c_i: Vector3<f64>,
    /// Query unit axis `a_i`.
    pub a_i: Vector3<f64>,
    /// Database origin `c_j`, body frame of `T_j`, metres.
    pub c_j: Vector3<f64>,
    /// Database unit axis `a_j`.
    pub a_j: Vector3<f64>,
    /// Rotation applied to the position residual and its Jacobian rows.
    pub frame: Matrix3<f64>,
}

/// The cross-product matrix `[v]x`.
fn skew(v: &Vector3<f64>) -> Matrix3<f64> {
    Matrix3::new(0.0, -v.z, v.y, v.z, 0.0, -v.x, -v.y, v.x, 0.0)
}

/// The residual `[frame r, delta]` of `pair` under poses `world_from_i`, `world_from_j`
/// (homogeneous 4 x 4), and, when `jacobians`, its Jacobians with respect to `T_i` and `T_j`.
pub fn landmark_residual(
    world_from_i: &Matrix4<f64>,
    world_from_j: &Matrix4<f64>,
    pair: &LandmarkPair,
    jacobians: bool,
) -> (Vector4<f64>, Option<(Jacobian, Jacobian)>) {
    let r_i: Matrix3<f64> = world_from_i.fixed_view::<3, 3>(0, 0).into_owned();
    let r_j: Matrix3<f64> = world_from_j.fixed_view::<3, 3>(0, 0).into_owned();
    let t_i: Vector3<f64> = world_from_i.fixed_view::<3, 1>(0, 3).into_owned();
    let t_j: Vector3<f64> = world_from_j.fixed_view::<3, 1>(0, 3).into_owned();
    let ri_t = r_i.transpose();
    let r_ij = ri_t * r_j;
    let t_ij = ri_t * (t_j - t_i);
    let q = r_ij * pair.c_j + t_ij;
    let b = r_ij * pair.a_j;
    let s = pair.a_i.dot(&b);
    let r = pair.frame * (q - pair.c_i);
    let res = Vector4::new(r.x, r.y, r.z, 1.0 - s * s);
    if !jacobians {
        return (res, None);
    }
    let mut hi = Jacobian::zeros();
    let mut hj = Jacobian::zeros();
    hi.fixed_view_mut::<3, 3>(0, 0)
        .copy_from(&(pair.frame * skew(&q)));
    hi.fixed_view_mut::<3, 3>(0, 3).copy_from(&(-pair.frame));
    hj.fixed_view_mut::<3, 3>(0, 0)
        .copy_from(&(-pair.frame * r_ij * skew(&pair.c_j)));
    hj.fixed_view_mut::<3, 3>(0, 3)
        .copy_from(&(pair.frame * r_ij));
    let di = -2.0 * s * (pair.a_i.transpose() * skew(&b));
    let dj = 2.0 * s * (pair.a_i.transpose() * r_ij * skew(&pair.a_j));
    hi.fixed_view_mut::<1, 3>(3, 0).copy_from(&di);
    hj.fixed_view_mut::<1, 3>(3, 0).copy_from(&dj);
    (res, Some((hi, hj)))
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{Isometry3, Translation3, UnitQuaternion};

    fn pose(axis: [f64; 3], angle: f64, t: [f64; 3]) -> Matrix4<f64> {
        let rotation = UnitQuaternion::from_scaled_axis(Vector3::from(axis) * angle);
        Isometry3::from_parts(Translation3::from(Vector3::from(t)), rotation).to_homogeneous()
    }

    /// `T Exp(xi)` for GTSAM's Pose3 chart `[w, v]` (to first order in `v`, exact in `w`).
    fn retract(t: &Matrix4<f64>, xi: &SMatrix<f64, 6, 1>) -> Matrix4<f64> {
        let w = Vector3::new(xi[0], xi[1], xi[2]);
        let v = Vector3::new(xi[3], xi[4], xi[5]);
        let delta =
            Isometry3::from_parts(Translation3::from(v), UnitQuaternion::from_scaled_axis(w));
        t * delta.to_homogeneous()
    }

    fn pair() -> LandmarkPair {
        let frame = UnitQuaternion::from_scaled_axis(Vector3::new(0.1, -0.3, 0.2))
            .to_rotation_matrix()
            .into_inner();
        LandmarkPair {
            c_i: Vector3::new(0.7, 0.05, -0.1),
            a_i: Vector3::new(1.0, 0.02, -0.01).normalize(),
            c_j: Vector3::new(-0.4, 0.1, 0.05),
            a_j: Vector3::new(-1.0, 0.03, 0.02).normalize(),
            frame,
        }
    }

    #[test]
    fn a_boundary_seen_at_one_place_along_one_axis_has_zero_residual_whatever_the_roll() {
        // T_j = T_i * offset, with c_j = offset^-1 c_i and a_j = -(offset^-1 a_i): the same
        // boundary from a reversed heading.
        let ti = pose([0.0, 0.0, 1.0], 0.3, [1.0, 2.0, 0.5]);
        let offset = pose([0.0, 0.0, 1.0], std::f64::consts::PI, [2.0, 0.0, 0.0]);
        let inv = offset.try_inverse().unwrap();
        let c_i = Vector3::new(0.8, 0.0, 0.0);
        let a_i = Vector3::new(1.0, 0.0, 0.0);
        let c_j = (inv * c_i.push(1.0)).xyz();
        let a_j = -(inv.fixed_view::<3, 3>(0, 0) * a_i);
        let p = LandmarkPair {
            c_i,
            a_i,
            c_j,
            a_j,
            frame: Matrix3::identity(),
        };
        let (res, _) = landmark_residual(&ti, &(ti * offset), &p, false);
        assert!(res.norm() < 1e-12, "{res}");
        // A roll of T_j about the axis through the landmark origin changes nothing.
        let about = pose([1.0, 0.0, 0.0], 0.7, [0.0; 3]);
        let through = Translation3::from(c_j).to_homogeneous();
        let rolled = ti * offset * through * about * through.try_inverse().unwrap();
        let (res, _) = landmark_residual(&ti, &rolled, &p, false);
        assert!(res.norm() < 1e-12, "{res}");
    }

    #[test]
    fn jacobians_match_central_differences() {
        let ti = pose([0.2, 0.5, 1.0], 0.4, [1.0, -2.0, 0.3]);
        let tj = pose([0.1, -0.2, 1.0], 2.9, [4.0, -1.5, 0.2]);
        let p = pair();
        let (_, jac) = landmark_residual(&ti, &tj, &p, true);
        let (hi, hj) = jac.unwrap();
        let h = 1e-6;
        for k in 0..6 {
            let mut xi = SMatrix::<f64, 6, 1>::zeros();
            xi[k] = h;
            let d_i = (landmark_residual(&retract(&ti, &xi), &tj, &p, false).0
                - landmark_residual(&retract(&ti, &(-xi)), &tj, &p, false).0)
                / (2.0 * h);
            let d_j = (landmark_residual(&ti, &retract(&tj, &xi), &p, false).0
                - landmark_residual(&ti, &retract(&tj, &(-xi)), &p, false).0)
                / (2.0 * h);
            assert!(
                (d_i - hi.column(k)).norm() < 1e-7,
                "i {k}: {d_i} vs {}",
                hi.column(k)
            );
            assert!(
                (d_j - hj.column(k)).norm() < 1e-7,
                "j {k}: {d_j} vs {}",
                hj.column(k)
            );
        }
    }
}
