//! Depth image → points through a pinhole camera with optional Brown-Conrady lens
//! distortion (OpenCV's model and pixel convention: pixel (u, v) has its centre at
//! (u, v); depth is the z coordinate in the camera frame, in metres).

use crate::error::{Error, Result};
use crate::na::Matrix4;

/// Pinhole intrinsics in pixels.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Intrinsics {
    pub fx: f64,
    pub fy: f64,
    pub cx: f64,
    pub cy: f64,
}

/// OpenCV's radial-tangential distortion (k1, k2, p1, p2, k3).
#[derive(Clone, Copy, Debug, PartialEq, Default)]
pub struct BrownConrady {
    pub k1: f64,
    pub k2: f64,
    pub p1: f64,
    pub p2: f64,
    pub k3: f64,
}

impl BrownConrady {
    /// Distort normalised image coordinates (x, y) → (x_d, y_d).
    #[inline]
    pub fn distort(&self, x: f64, y: f64) -> (f64, f64) {
        let r2 = x * x + y * y;
        let radial = 1.0 + r2 * (self.k1 + r2 * (self.k2 + r2 * self.k3));
        let xd = x * radial + 2.0 * self.p1 * x * y + self.p2 * (r2 + 2.0 * x * x);
        let yd = y * radial + self.p1 * (r2 + 2.0 * y * y) + 2.0 * self.p2 * x * y;
        (xd, yd)
    }

    /// Invert [`distort`](Self::distort) by fixed-point iteration (OpenCV's
    /// `undistortPoints` scheme), to well below a thousandth of a pixel for real lenses.
    #[inline]
    pub fn undistort(&self, xd: f64, yd: f64) -> (f64, f64) {
        let (mut x, mut y) = (xd, yd);
        for _ in 0..20 {
            let r2 = x * x + y * y;
            let radial = 1.0 + r2 * (self.k1 + r2 * (self.k2 + r2 * self.k3));
            let dx = 2.0 * self.p1 * x * y + self.p2 * (r2 + 2.0 * x * x);
            let dy = self.p1 * (r2 + 2.0 * y * y) + 2.0 * self.p2 * x * y;
            let (nx, ny) = ((xd - dx) / radial, (yd - dy) / radial);
            let converged = (nx - x).abs() < 1e-12 && (ny - y).abs() < 1e-12;
            (x, y) = (nx, ny);
            if converged {
                break;
            }
        }
        (x, y)
    }

    fn is_zero(&self) -> bool {
        *self == BrownConrady::default()
    }
}

/// A depth image (row-major, `width × height`; 0 or NaN = no reading). Depth in
/// metres is `depth × scale` (e.g. 0.001 for millimetre images).
pub struct DepthFrame<'a> {
    pub depth: &'a [f32],
    pub width: usize,
    pub height: usize,
    pub scale: f64,
}

/// Back-project every valid pixel: returns the points (camera frame, or map frame
/// when `base_from_camera` is given) and the index of the pixel each came from.
/// Valid means finite, > 0, ≥ `min_depth` and ≤ `max_depth`.
pub fn depth_to_points(
    frame: &DepthFrame,
    k: &Intrinsics,
    distortion: Option<&BrownConrady>,
    min_depth: f64,
    max_depth: f64,
    base_from_camera: Option<&Matrix4<f64>>,
) -> Result<(Vec<[f64; 3]>, Vec<u32>)> {
    if !(k.fx.is_finite()
        && k.fy.is_finite()
        && k.fx > 0.0
        && k.fy > 0.0
        && k.cx.is_finite()
        && k.cy.is_finite())
    {
        return Err(Error::InvalidArgument(format!(
            "intrinsics need finite fx, fy > 0 and finite cx, cy, got {k:?}"
        )));
    }
    if frame.depth.len() != frame.width * frame.height || frame.width == 0 || frame.height == 0 {
        return Err(Error::InvalidArgument(
            "depth image is empty or its size does not match".into(),
        ));
    }
    if u32::try_from(frame.depth.len()).is_err() {
        return Err(Error::InvalidArgument("depth image is too large".into()));
    }
    if !(frame.scale.is_finite() && frame.scale > 0.0) {
        return Err(Error::InvalidArgument(format!(
            "depth_scale must be positive, got {}",
            frame.scale
        )));
    }
    if !(min_depth >= 0.0 && max_depth > min_depth) {
        return Err(Error::InvalidArgument(format!(
            "need 0 <= min_depth < max_depth, got {min_depth}, {max_depth}"
        )));
    }
    if let Some(pose) = base_from_camera {
        crate::geometry::check_rigid(pose, "base_from_camera")?;
    }
    let distortion = distortion.filter(|d| !d.is_zero());
    let mut points = Vec::with_capacity(frame.depth.len());
    let mut pixels = Vec::with_capacity(frame.depth.len());
    for v in 0..frame.height {
        let row = &frame.depth[v * frame.width..(v + 1) * frame.width];
        let yd = (v as f64 - k.cy) / k.fy;
        for (u, &z) in row.iter().enumerate() {
            let z = f64::from(z) * frame.scale;
            if !(z > 0.0 && z >= min_depth && z <= max_depth) {
                continue; // also drops NaN
            }
            let xd = (u as f64 - k.cx) / k.fx;
            let (x, y) = match distortion {
                Some(d) => d.undistort(xd, yd),
                None => (xd, yd),
            };
            points.push([x * z, y * z, z]);
            pixels.push((v * frame.width + u) as u32);
        }
    }
    if let Some(pose) = base_from_camera {
        crate::geometry::transform_points(pose, &mut points);
    }
    Ok((points, pixels))
}
