//! Corridor axis and transverse basis (paper §III-A, Eq. 1).
//!
//! The axis `a` is the principal direction of the submap (PCA); the corridor is accepted
//! only if the ratio of the two largest singular values is at least `axis.min_elongation`
//! (2.0 in the paper, §IV-A.2). The basis `e1 = normalize((I - a a^T) g)`, `e2 = a x e1`
//! (Eq. 1) fixes the circumferential origin `p = 0` at gravity, i.e. at the bottom of the
//! section, so that revisits need no rotational search.

use nalgebra::{Matrix3, SymmetricEigen, Vector3};

use crate::error::{DecodError, Result};

/// The corridor axis of one submap (all in the submap frame).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct CorridorAxis {
    /// Mean of the points, metres.
    pub centroid: [f64; 3],
    /// Unit principal direction, oriented so that `axis . forward >= 0`.
    pub axis: [f64; 3],
    /// Singular values of the centred cloud scaled by `1/sqrt(N)` (standard deviations
    /// along the principal directions), descending, metres.
    pub singular_values: [f64; 3],
    /// `singular_values[0] / singular_values[1]`: the elongation the check uses.
    pub elongation: f64,
    /// The three unit principal directions in the order of `singular_values` (the first is
    /// `axis`), each oriented so that `direction . forward >= 0`: the candidates for the
    /// axis of a submap whose cloud is not elongated (`crate::extract`, corridor ends).
    pub directions: [[f64; 3]; 3],
}

/// The mean of `points` in f64, metres (NaN for none).
pub fn centroid(points: &[[f32; 3]]) -> [f64; 3] {
    let mut sum = Vector3::zeros();
    for p in points {
        sum += Vector3::new(p[0] as f64, p[1] as f64, p[2] as f64);
    }
    let mean = sum / points.len() as f64;
    [mean.x, mean.y, mean.z]
}

/// PCA of `points` (paper §III-A); the axis is oriented with `forward` (paper §IV-A.2).
///
/// Accumulates the mean and covariance in f64 in one pass each (no copy of the cloud).
/// Errors on fewer than 3 points.
pub fn estimate_axis(points: &[[f32; 3]], forward: [f64; 3]) -> Result<CorridorAxis> {
    if points.len() < 3 {
        return Err(DecodError::invalid(
            "points",
            format!("PCA needs at least 3 points, got {}", points.len()),
        ));
    }
    let n = points.len() as f64;
    let mean = Vector3::from(centroid(points));
    let mut cov = Matrix3::zeros();
    for p in points {
        let d = Vector3::new(p[0] as f64, p[1] as f64, p[2] as f64) - mean;
        cov += d * d.transpose();
    }
    cov /= n;
    let (values, vectors) = eigen_descending(&cov);
    let sv = values.map(|v| v.max(0.0).sqrt());
    let directions = vectors.map(|d| along(d, forward));
    let elongation = if sv[1] > 0.0 {
        sv[0] / sv[1]
    } else {
        f64::INFINITY
    };
    Ok(CorridorAxis {
        centroid: [mean.x, mean.y, mean.z],
        axis: directions[0],
        singular_values: sv,
        elongation,
        directions,
    })
}

/// The eigenvalues of a symmetric 3x3 matrix, largest first, and their unit eigenvectors in
/// the same order.
pub(crate) fn eigen_descending(m: &Matrix3<f64>) -> ([f64; 3], [Vector3<f64>; 3]) {
    let eig = SymmetricEigen::new(*m);
    let mut order = [0usize, 1, 2];
    order.sort_by(|&i, &j| eig.eigenvalues[j].total_cmp(&eig.eigenvalues[i]));
    (
        order.map(|i| eig.eigenvalues[i]),
        order.map(|i| eig.eigenvectors.column(i).into_owned()),
    )
}

/// `v` turned, if need be, to point with `forward` (`v . forward >= 0`; paper §IV-A.2).
pub(crate) fn along(v: Vector3<f64>, forward: [f64; 3]) -> [f64; 3] {
    let v = if v.dot(&Vector3::from(forward)) < 0.0 {
        -v
    } else {
        v
    };
    [v.x, v.y, v.z]
}

/// The angle between two unit directions, deg (0-180).
pub fn angle_deg(a: [f64; 3], b: [f64; 3]) -> f64 {
    (a[0] * b[0] + a[1] * b[1] + a[2] * b[2])
        .clamp(-1.0, 1.0)
        .acos()
        .to_degrees()
}

/// One Gauss–Newton step on the axis direction, given points unrolled on a contour fitted
/// with the current axis (not in the paper; PCA alone leaves ~0.1 deg of error on a 3 m
/// pipe, which tilts the section by 3 mm at the ends and leaks into the boundary profile).
///
/// A centre line `delta(z) = delta0 + z t` (in `(e1, e2)`, metres) shifts the offset of a
/// point with outward normal `n` by `n . delta(z)`. Least squares of
/// `s_i = n_i . delta0 + z_i n_i . t` over the points with `|s_i| <= max_abs_offset_m`
/// (the robust inliers) gives the tilt `t`; the corrected axis is
/// `normalize(a + t1 e1 + t2 e2)`. `samples` are `(z, n1, n2, s)`. Returns `None` when the
/// system is singular (too few points or normals all alike).
pub fn refine_axis(
    axis: [f64; 3],
    e1: [f64; 3],
    e2: [f64; 3],
    samples: impl Iterator<Item = (f64, f64, f64, f64)>,
    max_abs_offset_m: f64,
) -> Option<[f64; 3]> {
    let mut h = nalgebra::Matrix4::<f64>::zeros();
    let mut g = nalgebra::Vector4::<f64>::zeros();
    for (z, n1, n2, s) in samples {
        if s.abs() > max_abs_offset_m {
            continue;
        }
        let j = nalgebra::Vector4::new(n1, n2, z * n1, z * n2);
        h += j * j.transpose();
        g += j * s;
    }
    let x = h.lu().solve(&g)?;
    let v = Vector3::from(axis) + Vector3::from(e1) * x[2] + Vector3::from(e2) * x[3];
    let v = v.try_normalize(1e-12)?;
    v.iter().all(|c| c.is_finite()).then_some([v.x, v.y, v.z])
}

/// The transverse basis of Eq. 1: `e1 = normalize((I - a a^T) g)` with `g` the gravity
/// direction (pointing down), `e2 = a x e1`. Errors when gravity is (nearly) along the axis
/// (a vertical shaft: the circumferential origin is undefined; the threshold is 1e-3 of the
/// projected norm, i.e. an axis within 0.06 deg of vertical).
pub fn transverse_basis(axis: [f64; 3], gravity: [f64; 3]) -> Result<([f64; 3], [f64; 3])> {
    let a = Vector3::from(axis);
    let g = Vector3::from(gravity);
    let projected = g - a * a.dot(&g);
    let norm = projected.norm();
    if norm.is_nan() || norm <= 1e-3 * g.norm() {
        return Err(DecodError::invalid(
            "gravity",
            "is parallel to the corridor axis: no circumferential origin (vertical shaft)",
        ));
    }
    let e1 = projected / norm;
    let e2 = a.cross(&e1);
    Ok(([e1.x, e1.y, e1.z], [e2.x, e2.y, e2.z]))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn cylinder(n: usize, axis: Vector3<f64>, radius: f64, length: f64) -> Vec<[f32; 3]> {
        let a = axis.normalize();
        let u = a.cross(&Vector3::z()).normalize();
        let v = a.cross(&u);
        (0..n)
            .map(|i| {
                let t = (i as f64 * 0.618_033_988_7).fract() * std::f64::consts::TAU;
                let z = (i as f64 / n as f64 - 0.5) * length;
                let p = a * z + (u * t.cos() + v * t.sin()) * radius + Vector3::new(1.0, -2.0, 0.5);
                [p.x as f32, p.y as f32, p.z as f32]
            })
            .collect()
    }

    #[test]
    fn cylinder_axis_is_found_and_oriented_forward() {
        let true_axis = Vector3::new(1.0, 0.2, 0.1).normalize();
        let pts = cylinder(20_000, true_axis, 0.3, 4.0);
        let ax = estimate_axis(&pts, [-1.0, 0.0, 0.0]).unwrap();
        let a = Vector3::from(ax.axis);
        // Oriented with forward = -x, so a points against true_axis.
        assert!(a.dot(&true_axis) < -0.99999, "{a:?}");
        assert!(ax.elongation > 5.0);
    }

    #[test]
    fn basis_is_orthonormal_with_e1_down() {
        let (e1, e2) = transverse_basis([1.0, 0.0, 0.0], [0.1, 0.0, -1.0]).unwrap();
        assert!((e1[2] + 1.0).abs() < 1e-12 && e1[0].abs() < 1e-12);
        // e2 = x cross -z = +y.
        assert!((e2[1] - 1.0).abs() < 1e-12);
        assert!(transverse_basis([0.0, 0.0, 1.0], [0.0, 0.0, -1.0]).is_err());
        assert!(estimate_axis(&[[0.0; 3]; 2], [1.0, 0.0, 0.0]).is_err());
    }
}
