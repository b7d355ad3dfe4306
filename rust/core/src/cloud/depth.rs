//! Depth image → points through a pinhole camera with optional Brown-Conrady lens
//! distortion (OpenCV's model and pixel convention: pixel (u, v) has its centre at
//! (u, v); depth is the z coordinate in the camera frame, in metres).

use std::sync::{Arc, Mutex, OnceLock};

use crate::error::{Error, Result};
use crate::geometry::{cross, dot};
use crate::na::Matrix4;

/// Pinhole intrinsics in pixels.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Intrinsics {
    /// Focal length along the image x axis, in pixels.
    pub fx: f64,
    /// Focal length along the image y axis, in pixels.
    pub fy: f64,
    /// Principal point, x (column), in pixels.
    pub cx: f64,
    /// Principal point, y (row), in pixels.
    pub cy: f64,
}

/// OpenCV's radial-tangential distortion (k1, k2, p1, p2, k3).
#[derive(Clone, Copy, Debug, PartialEq, Default)]
pub struct BrownConrady {
    /// First radial coefficient.
    pub k1: f64,
    /// Second radial coefficient.
    pub k2: f64,
    /// First tangential coefficient.
    pub p1: f64,
    /// Second tangential coefficient.
    pub p2: f64,
    /// Third radial coefficient.
    pub k3: f64,
}

impl BrownConrady {
    /// The radial factor 1 + k1 r² + k2 r⁴ + k3 r⁶ at `r2` = r².
    #[inline]
    fn radial(&self, r2: f64) -> f64 {
        1.0 + r2 * (self.k1 + r2 * (self.k2 + r2 * self.k3))
    }

    /// Distort normalised image coordinates (x, y) → (x_d, y_d).
    #[inline]
    pub fn distort(&self, x: f64, y: f64) -> (f64, f64) {
        let r2 = x * x + y * y;
        let radial = self.radial(r2);
        let xd = x * radial + 2.0 * self.p1 * x * y + self.p2 * (r2 + 2.0 * x * x);
        let yd = y * radial + self.p1 * (r2 + 2.0 * y * y) + 2.0 * self.p2 * x * y;
        (xd, yd)
    }

    /// Invert [`distort`](Self::distort) by fixed-point iteration (OpenCV's
    /// `undistortPoints` scheme), to well below a thousandth of a pixel for real lenses;
    /// where that has not settled in 20 rounds (it crawls near a wide lens's edge),
    /// Newton's steps finish it.
    #[inline]
    pub fn undistort(&self, xd: f64, yd: f64) -> (f64, f64) {
        let (mut x, mut y) = (xd, yd);
        for _ in 0..20 {
            let r2 = x * x + y * y;
            let radial = self.radial(r2);
            let dx = 2.0 * self.p1 * x * y + self.p2 * (r2 + 2.0 * x * x);
            let dy = self.p1 * (r2 + 2.0 * y * y) + 2.0 * self.p2 * x * y;
            let (nx, ny) = ((xd - dx) / radial, (yd - dy) / radial);
            let converged = (nx - x).abs() < 1e-12 && (ny - y).abs() < 1e-12;
            (x, y) = (nx, ny);
            if converged {
                return (x, y);
            }
        }
        for _ in 0..12 {
            let (ux, uy) = self.distort(x, y);
            let (ex, ey) = (ux - xd, uy - yd);
            let [[a, b], [c, d]] = self.jacobian(x, y);
            let det = a * d - b * c;
            if !(det.is_finite() && det != 0.0) || (ex.abs() < 1e-15 && ey.abs() < 1e-15) {
                break;
            }
            (x, y) = (x - (d * ex - b * ey) / det, y - (a * ey - c * ex) / det);
        }
        (x, y)
    }

    /// ∂(x_d, y_d) / ∂(x, y) of [`distort`](Self::distort), row by row.
    fn jacobian(&self, x: f64, y: f64) -> [[f64; 2]; 2] {
        let r2 = x * x + y * y;
        let radial = self.radial(r2);
        // d radial / d r², times 2 for d r² / dx = 2x.
        let slope = 2.0 * (self.k1 + r2 * (2.0 * self.k2 + 3.0 * r2 * self.k3));
        [
            [
                radial + x * x * slope + 2.0 * self.p1 * y + 6.0 * self.p2 * x,
                x * y * slope + 2.0 * self.p1 * x + 2.0 * self.p2 * y,
            ],
            [
                x * y * slope + 2.0 * self.p1 * x + 2.0 * self.p2 * y,
                radial + y * y * slope + 6.0 * self.p1 * y + 2.0 * self.p2 * x,
            ],
        ]
    }

    /// [`undistort`](Self::undistort) where the lens reaches (x_d, y_d): `None` where
    /// no ray on the lens's unfolded side distorts to within `tolerance` of it (a
    /// strong barrel lens folds back before an image's corners: past the fold the
    /// image shrinks again, and the inversion there is another ray's or none).
    pub fn invert(&self, xd: f64, yd: f64, tolerance: [f64; 2]) -> Option<(f64, f64)> {
        let (x, y) = self.undistort(xd, yd);
        let (ux, uy) = self.distort(x, y);
        let [[a, b], [c, d]] = self.jacobian(x, y);
        // Before the fold: the image grows outwards (a positive Jacobian) and is not
        // turned through the centre (a positive radial factor; beyond, both signs of
        // a radial lens's factors flip and the Jacobian is positive again).
        let unfolded = self.radial(x * x + y * y) > 0.0 && a * d - b * c > 0.0;
        (unfolded && (ux - xd).abs() <= tolerance[0] && (uy - yd).abs() <= tolerance[1])
            .then_some((x, y))
    }

    fn is_zero(&self) -> bool {
        *self == BrownConrady::default()
    }
}

/// A depth image (row-major, `width × height`; 0, NaN or ∞ = no reading). Depth in
/// metres is `depth × scale` (e.g. 0.001 for millimetre images).
pub struct DepthFrame<'a> {
    /// Depth readings, row-major, `width × height` of them.
    pub depth: &'a [f32],
    /// Image width in pixels.
    pub width: usize,
    /// Image height in pixels.
    pub height: usize,
    /// Metres per depth unit.
    pub scale: f64,
}

/// Back-project every valid pixel: returns the points (camera frame, or map frame
/// when `base_from_camera` is given) and the index of the pixel each came from.
/// Valid means finite, > 0, ≥ `min_depth` and ≤ `max_depth`, at a pixel the lens
/// reaches (a strong barrel `distortion` may fold back before the image's corners).
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
            "intrinsics need finite fx, fy > 0 and finite cx, cy, got fx = {}, fy = {}, cx = {}, cy = {}",
            k.fx, k.fy, k.cx, k.cy
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
    if let Some(d) = distortion {
        if ![d.k1, d.k2, d.p1, d.p2, d.k3].iter().all(|c| c.is_finite()) {
            return Err(Error::InvalidArgument(format!(
                "distortion coefficients must be finite, got k1={} k2={} p1={} p2={} k3={}",
                d.k1, d.k2, d.p1, d.p2, d.k3
            )));
        }
    }
    // A lens's undistorted rays are the same every frame: inverted once per lens.
    let rays = distortion
        .filter(|d| !d.is_zero())
        .map(|d| ray_table(k, d, frame.width, frame.height));
    let mut points = Vec::with_capacity(frame.depth.len());
    let mut pixels = Vec::with_capacity(frame.depth.len());
    for v in 0..frame.height {
        let row = &frame.depth[v * frame.width..(v + 1) * frame.width];
        let yd = (v as f64 - k.cy) / k.fy;
        for (u, &z) in row.iter().enumerate() {
            let z = f64::from(z) * frame.scale;
            if !(z > 0.0 && z >= min_depth && z <= max_depth && z.is_finite()) {
                continue; // also drops NaN and infinite readings (no reading)
            }
            let (x, y) = match &rays {
                Some(table) => {
                    let r = table[v * frame.width + u];
                    if r[0].is_nan() {
                        continue; // beyond what the lens reaches
                    }
                    (r[0], r[1])
                }
                None => ((u as f64 - k.cx) / k.fx, yd),
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

/// How close (pixels) a ray must land on a pixel for the lens to reach it.
const REACH_PIXELS: f64 = 0.01;

type LensKey = [u64; 11];
/// Per-pixel undistorted rays of one lens.
type RayTable = Arc<Vec<[f64; 2]>>;

/// The undistorted normalised ray (x, y) of every pixel of a `width × height` image
/// through `k` and `d` (NaN for a pixel the lens does not reach, to a hundredth of a
/// pixel), computed once per lens and kept for the next calls (the last eight lenses:
/// one per camera of a cell).
fn ray_table(k: &Intrinsics, d: &BrownConrady, width: usize, height: usize) -> RayTable {
    static CACHE: OnceLock<Mutex<Vec<(LensKey, RayTable)>>> = OnceLock::new();
    let key: LensKey = [
        width as u64,
        height as u64,
        k.fx.to_bits(),
        k.fy.to_bits(),
        k.cx.to_bits(),
        k.cy.to_bits(),
        d.k1.to_bits(),
        d.k2.to_bits(),
        d.p1.to_bits(),
        d.p2.to_bits(),
        d.k3.to_bits(),
    ];
    let cache = CACHE.get_or_init(|| Mutex::new(Vec::new()));
    // A panic elsewhere while holding the lock leaves the cache usable.
    if let Some((_, table)) = cache
        .lock()
        .unwrap_or_else(|e| e.into_inner())
        .iter()
        .find(|(k2, _)| *k2 == key)
    {
        return Arc::clone(table);
    }
    let mut table = Vec::with_capacity(width * height);
    let tolerance = [REACH_PIXELS / k.fx, REACH_PIXELS / k.fy];
    for v in 0..height {
        let yd = (v as f64 - k.cy) / k.fy;
        for u in 0..width {
            let ray = d.invert((u as f64 - k.cx) / k.fx, yd, tolerance);
            table.push(ray.map_or([f64::NAN; 2], |(x, y)| [x, y]));
        }
    }
    let table = Arc::new(table);
    let mut entries = cache.lock().unwrap_or_else(|e| e.into_inner());
    entries.insert(0, (key, Arc::clone(&table)));
    entries.truncate(8);
    table
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Points through the cached ray tables equal the per-pixel inversion, for two
    /// lenses used in turn (the cache must not mix them up).
    #[test]
    fn cached_rays_match_the_direct_inversion() {
        let (w, h) = (40, 30);
        let depth: Vec<f32> = (0..w * h).map(|i| 0.5 + (i % 7) as f32 * 0.1).collect();
        let frame = DepthFrame {
            depth: &depth,
            width: w,
            height: h,
            scale: 1.0,
        };
        let k = Intrinsics {
            fx: 30.0,
            fy: 31.0,
            cx: 19.5,
            cy: 14.5,
        };
        let lenses = [
            BrownConrady {
                k1: 0.09,
                k2: -0.27,
                p1: 0.001,
                p2: -0.002,
                k3: 0.09,
            },
            BrownConrady {
                k1: -0.1,
                k2: 0.25,
                ..Default::default()
            },
        ];
        for round in 0..2 {
            for d in &lenses {
                let (points, pixels) =
                    depth_to_points(&frame, &k, Some(d), 0.0, 10.0, None).unwrap();
                assert_eq!(points.len(), w * h, "round {round}");
                for (p, &i) in points.iter().zip(&pixels) {
                    let (u, v) = (i as usize % w, i as usize / w);
                    let (x, y) = d.undistort((u as f64 - k.cx) / k.fx, (v as f64 - k.cy) / k.fy);
                    let z = f64::from(depth[i as usize]);
                    assert_eq!(*p, [x * z, y * z, z]);
                }
            }
        }
    }

    /// A `w × h` depth image of `depth` in metres.
    fn wall(depth: &[f32], w: usize, h: usize) -> DepthFrame<'_> {
        DepthFrame {
            depth,
            width: w,
            height: h,
            scale: 1.0,
        }
    }

    /// A `w × h` camera of focal length `f` pixels, its principal point at the centre.
    fn centred(w: usize, h: usize, f: f64) -> Intrinsics {
        Intrinsics {
            fx: f,
            fy: f,
            cx: (w as f64 - 1.0) / 2.0,
            cy: (h as f64 - 1.0) / 2.0,
        }
    }

    /// A barrel lens strong enough to fold back before the image's corners: the pixels
    /// it cannot reach give no point (they gave points metres off, wherever the
    /// iteration wandered); every pixel it reaches gives the ray that distorts onto it.
    #[test]
    fn pixels_beyond_the_lens_reach_give_no_point() {
        let (w, h) = (64, 48);
        let depth = vec![1.0f32; w * h];
        let (frame, k) = (wall(&depth, w, h), centred(w, h, 40.0));
        let d = BrownConrady {
            k1: -0.5,
            ..Default::default()
        };
        // r (1 - r²/2) peaks at r = √(2/3), distorted radius 0.544: 21.8 px from the centre.
        let reach = 40.0 * (2.0f64 / 3.0).sqrt() * (1.0 - 1.0 / 3.0);
        let (points, pixels) = depth_to_points(&frame, &k, Some(&d), 0.0, 10.0, None).unwrap();
        let radius = |i: u32| {
            let (u, v) = (
                (i as usize % w) as f64 - k.cx,
                (i as usize / w) as f64 - k.cy,
            );
            (u * u + v * v).sqrt()
        };
        assert!(pixels.iter().all(|&i| radius(i) <= reach + 0.01));
        let kept: std::collections::HashSet<u32> = pixels.iter().copied().collect();
        let inside = (0..(w * h) as u32).filter(|&i| radius(i) < reach - 0.5);
        assert!(inside.clone().all(|i| kept.contains(&i)));
        assert!(points.len() < w * h && inside.count() > 1000);
        for (p, &i) in points.iter().zip(&pixels) {
            let (xd, yd) = d.distort(p[0], p[1]);
            let (u, v) = (i as usize % w, i as usize / w);
            assert!((xd * k.fx + k.cx - u as f64).abs() < 0.01, "{p:?} {u}");
            assert!((yd * k.fy + k.cy - v as f64).abs() < 0.01, "{p:?} {v}");
        }
    }

    /// Wide lenses that never fold (their radial curve rises everywhere), where the
    /// fixed-point iteration crawls at the edges: every pixel gets the ray that distorts
    /// onto it, to well within a hundredth of a pixel.
    #[test]
    fn every_pixel_of_a_lens_that_does_not_fold_gives_its_ray() {
        let (w, h) = (640, 480);
        let depth = vec![1.0f32; w * h];
        let (frame, k) = (wall(&depth, w, h), centred(w, h, 300.0));
        for (k1, k2) in [(-0.28, 0.07), (1.0, 0.0), (0.2, 0.3)] {
            let d = BrownConrady {
                k1,
                k2,
                ..Default::default()
            };
            let (points, _) = depth_to_points(&frame, &k, Some(&d), 0.0, 10.0, None).unwrap();
            assert_eq!(points.len(), w * h, "k1 {k1}, k2 {k2}");
            let worst = points
                .iter()
                .zip(0..)
                .map(|(p, i): (&[f64; 3], usize)| {
                    let (xd, yd) = d.distort(p[0], p[1]);
                    let (u, v) = ((i % w) as f64, (i / w) as f64);
                    (xd * k.fx + k.cx - u)
                        .abs()
                        .max((yd * k.fy + k.cy - v).abs())
                })
                .fold(0.0f64, f64::max);
            assert!(worst < 1e-6, "k1 {k1}, k2 {k2}: {worst} px");
        }
    }
}

/// The cosine of the angle between each pixel's viewing ray and the surface normal estimated
/// from the depth image of a pinhole camera with focal lengths `fx`, `fy` and its
/// principal point at the image's centre. The normal is the cross product of the
/// back-projected points' gradients along the row and the column (central
/// differences, one-sided at the border); NaN where the pixel or a neighbour the
/// differences read has no depth (≤ 0), or the surface is degenerate. `depth` is
/// row-major, `width` × `height` (both ≥ 2).
pub fn incidence_cosines(
    depth: &[f64],
    width: usize,
    height: usize,
    fx: f64,
    fy: f64,
) -> Result<Vec<f64>> {
    if width < 2 || height < 2 || depth.len() != width * height {
        return Err(Error::InvalidArgument(format!(
            "incidence angles need a depth image of at least 2×2 pixels with width × height values, got {width}×{height} and {}",
            depth.len()
        )));
    }
    if !(fx.is_finite() && fy.is_finite() && fx > 0.0 && fy > 0.0) {
        return Err(Error::InvalidArgument(format!(
            "focal lengths must be positive, got fx={fx} fy={fy}"
        )));
    }
    let (cx, cy) = ((width - 1) as f64 / 2.0, (height - 1) as f64 / 2.0);
    // Back-projected once: NaN where there is no depth, so every difference that
    // reads such a pixel is NaN too.
    let points: Vec<[f64; 3]> = depth
        .iter()
        .enumerate()
        .map(|(i, &z)| {
            let z = if z > 0.0 { z } else { f64::NAN };
            [
                z * ((i % width) as f64 - cx) / fx,
                z * ((i / width) as f64 - cy) / fy,
                z,
            ]
        })
        .collect();
    // np.gradient's differences: central inside, one-sided at the two ends.
    let diff = |lo: usize, hi: usize, step: f64| {
        let (a, b) = (points[lo], points[hi]);
        [
            (b[0] - a[0]) / step,
            (b[1] - a[1]) / step,
            (b[2] - a[2]) / step,
        ]
    };
    let mut out = Vec::with_capacity(depth.len());
    for r in 0..height {
        let row = r * width;
        let (up, down, vstep) = match r {
            0 => (row, row + width, 1.0),
            r if r == height - 1 => (row - width, row, 1.0),
            _ => (row - width, row + width, 2.0),
        };
        for c in 0..width {
            let i = row + c;
            let p = points[i];
            if p[2].is_nan() {
                out.push(f64::NAN);
                continue;
            }
            let du = match c {
                0 => diff(i, i + 1, 1.0),
                c if c == width - 1 => diff(i - 1, i, 1.0),
                _ => diff(i - 1, i + 1, 2.0),
            };
            let dv = diff(up + c, down + c, vstep);
            let n = cross(&du, &dv);
            let norm2 = dot(&n, &n);
            let cos = dot(&n, &p).abs() / (norm2 * dot(&p, &p)).sqrt();
            out.push(if norm2 > 0.0 && cos.is_finite() {
                cos.min(1.0)
            } else {
                f64::NAN
            });
        }
    }
    Ok(out)
}

#[cfg(test)]
mod incidence_tests {
    use super::incidence_cosines;

    #[test]
    fn a_tilted_plane_gives_the_angle_between_ray_and_normal() {
        // The plane z = 2 + 0.5 x (normal (-0.5, 0, 1)) seen by a pinhole: depth per
        // pixel from the ray (x, y, 1) t, t = 2 / (1 - 0.5 x).
        let (w, h, f) = (9, 7, 10.0);
        let (cx, cy) = (4.0, 3.0);
        let depth: Vec<f64> = (0..w * h)
            .map(|i| {
                let x = ((i % w) as f64 - cx) / f;
                2.0 / (1.0 - 0.5 * x)
            })
            .collect();
        let angles: Vec<f64> = incidence_cosines(&depth, w, h, f, f)
            .unwrap()
            .iter()
            .map(|c| c.acos())
            .collect();
        let normal = [-0.5, 0.0, 1.0];
        let nn = (0.25f64 + 1.0).sqrt();
        for (i, a) in angles.iter().enumerate() {
            let ray = [((i % w) as f64 - cx) / f, ((i / w) as f64 - cy) / f, 1.0];
            let rn = (ray[0] * ray[0] + ray[1] * ray[1] + 1.0f64).sqrt();
            let expected = ((ray[0] * normal[0] + ray[2] * normal[2]).abs() / (rn * nn)).acos();
            assert!((a - expected).abs() < 1e-9, "pixel {i}: {a} vs {expected}");
        }
    }

    #[test]
    fn holes_give_nan_around_them() {
        let mut depth = vec![1.0; 16];
        depth[5] = 0.0;
        let angles = incidence_cosines(&depth, 4, 4, 5.0, 5.0).unwrap();
        // The hole, its row neighbours and its column neighbours read it.
        for i in [5, 4, 6, 1, 9] {
            assert!(angles[i].is_nan(), "pixel {i}");
        }
        assert!(angles[15].is_finite());
        assert!(incidence_cosines(&depth, 1, 16, 5.0, 5.0).is_err());
    }
}
