//! Rigid transforms as 4×4 homogeneous matrices (`target_from_source`).

use crate::error::{Error, Result};
use crate::na::Matrix4;

/// Check that `m` is a finite rigid transform: orthonormal rotation with det +1
/// (to 1e-6) and a bottom row of (0, 0, 0, 1).
pub fn check_rigid(m: &Matrix4<f64>, name: &str) -> Result<()> {
    if !m.iter().all(|v| v.is_finite()) {
        return Err(Error::InvalidArgument(format!(
            "{name} has non-finite entries"
        )));
    }
    let bottom = [m[(3, 0)], m[(3, 1)], m[(3, 2)], m[(3, 3)]];
    if bottom != [0.0, 0.0, 0.0, 1.0] {
        return Err(Error::InvalidArgument(format!(
            "{name} must end with the row (0, 0, 0, 1), got {bottom:?}"
        )));
    }
    let r = m.fixed_view::<3, 3>(0, 0);
    let err = (r.transpose() * r - crate::na::Matrix3::identity())
        .abs()
        .max();
    if err > 1e-6 || r.determinant() < 0.0 {
        return Err(Error::InvalidArgument(format!(
            "{name} is not a rigid transform (rotation part off orthonormal by {err:.2e} or a reflection)"
        )));
    }
    Ok(())
}

/// Apply `m` to every point in place.
pub fn transform_points(m: &Matrix4<f64>, points: &mut [[f64; 3]]) {
    let r = m.fixed_view::<3, 3>(0, 0).into_owned();
    let t = m.fixed_view::<3, 1>(0, 3).into_owned();
    for p in points {
        let q = r * crate::na::Vector3::new(p[0], p[1], p[2]) + t;
        *p = [q.x, q.y, q.z];
    }
}
