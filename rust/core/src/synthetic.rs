//! Depth frames of analytic scenes (spheres, boxes, a floor) for tests, benchmarks
//! and demos: every pixel's ray is intersected with every shape, so the geometry
//! behind each point is known exactly.

use crate::na::{Matrix4, Point3, Vector3};

/// Pinhole depth camera (x right, y down, z forward).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PinholeCamera {
    /// Image width in pixels.
    pub width: usize,
    /// Image height in pixels.
    pub height: usize,
    /// Focal length along x, in pixels.
    pub fx: f64,
    /// Focal length along y, in pixels.
    pub fy: f64,
    /// Principal point, x, in pixels.
    pub cx: f64,
    /// Principal point, y, in pixels.
    pub cy: f64,
    /// Farthest depth (camera z) reported, in metres.
    pub max_depth: f64,
}

impl PinholeCamera {
    /// Kinect V2-like depth camera: 512×424 pixels, ~70°×60° field of view.
    pub fn kinect_v2(max_depth: f64) -> Self {
        PinholeCamera {
            width: 512,
            height: 424,
            fx: 365.0,
            fy: 365.0,
            cx: 256.0,
            cy: 212.0,
            max_depth,
        }
    }
}

/// A shape of a synthetic scene (metres, map frame).
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Shape {
    /// A ball.
    Sphere {
        /// Centre of the ball.
        center: [f64; 3],
        /// Radius of the ball.
        radius: f64,
    },
    /// Axis-aligned box.
    Box {
        /// Lower corner.
        lo: [f64; 3],
        /// Upper corner.
        hi: [f64; 3],
    },
    /// The plane z = `z`.
    Floor {
        /// Height of the plane.
        z: f64,
    },
}

impl Shape {
    /// Distance along the unit ray to the first surface ahead, if any.
    fn intersect(&self, o: &Point3<f64>, d: &Vector3<f64>) -> Option<f64> {
        const EPS: f64 = 1e-9;
        match *self {
            Shape::Sphere { center, radius } => {
                let oc = o - Point3::from(center);
                let b = d.dot(&oc);
                let disc = b * b - (oc.norm_squared() - radius * radius);
                if disc < 0.0 {
                    return None;
                }
                let s = disc.sqrt();
                [-b - s, -b + s].into_iter().find(|&t| t > EPS)
            }
            Shape::Box { lo, hi } => {
                let (mut near, mut far) = (f64::NEG_INFINITY, f64::INFINITY);
                for a in 0..3 {
                    if d[a] == 0.0 {
                        if o[a] < lo[a] || o[a] > hi[a] {
                            return None;
                        }
                        continue;
                    }
                    let (t1, t2) = ((lo[a] - o[a]) / d[a], (hi[a] - o[a]) / d[a]);
                    near = near.max(t1.min(t2));
                    far = far.min(t1.max(t2));
                }
                if far < near.max(0.0) || far <= EPS {
                    None
                } else if near > EPS {
                    Some(near)
                } else {
                    Some(far)
                }
            }
            Shape::Floor { z } => {
                let t = (z - o.z) / d.z;
                (t.is_finite() && t > EPS).then_some(t)
            }
        }
    }
}

/// `base_from_camera` for a camera at `eye` looking at `target`, z forward and y down.
pub fn look_at(eye: [f64; 3], target: [f64; 3], up: [f64; 3]) -> Matrix4<f64> {
    let eye = Vector3::from(eye);
    let z = (Vector3::from(target) - eye).normalize();
    let mut x = z.cross(&Vector3::from(up));
    if x.norm() < 1e-9 {
        x = z.cross(&Vector3::x());
    }
    let x = x.normalize();
    let y = z.cross(&x);
    let mut m = Matrix4::identity();
    m.fixed_view_mut::<3, 1>(0, 0).copy_from(&x);
    m.fixed_view_mut::<3, 1>(0, 1).copy_from(&y);
    m.fixed_view_mut::<3, 1>(0, 2).copy_from(&z);
    m.fixed_view_mut::<3, 1>(0, 3).copy_from(&eye);
    m
}

/// The points (map frame) a camera at `base_from_camera` sees, row by row; pixels
/// that hit nothing within `max_depth` give no point.
pub fn render_points(
    camera: &PinholeCamera,
    base_from_camera: &Matrix4<f64>,
    shapes: &[Shape],
) -> Vec<[f64; 3]> {
    let rot = base_from_camera.fixed_view::<3, 3>(0, 0).into_owned();
    let o = Point3::from(base_from_camera.fixed_view::<3, 1>(0, 3).into_owned());
    let row = |v: usize| -> Vec<[f64; 3]> {
        let mut out = Vec::with_capacity(camera.width);
        for u in 0..camera.width {
            let ray_cam = Vector3::new(
                (u as f64 + 0.5 - camera.cx) / camera.fx,
                (v as f64 + 0.5 - camera.cy) / camera.fy,
                1.0,
            )
            .normalize();
            let d = rot * ray_cam;
            let t = shapes
                .iter()
                .filter_map(|s| s.intersect(&o, &d))
                .fold(f64::INFINITY, f64::min);
            if t.is_finite() && t * ray_cam.z <= camera.max_depth {
                let p = o + d * t;
                out.push([p.x, p.y, p.z]);
            }
        }
        out
    };
    // The core's pool, not rayon's global one (which a forked child cannot use).
    let v: Vec<usize> = (0..camera.height).collect();
    let rows = crate::threads::map_parts(&v, |&v| row(v));
    rows.concat()
}

/// The scene the benchmarks share (criterion and the Python comparison): a floor, a
/// table and clutter in a 3 m cell, seen by a Kinect V2-like camera from 2.6 m away;
/// with a 3 m depth limit about 217k of its 217k pixels return a point.
pub fn benchmark_scene() -> (PinholeCamera, Matrix4<f64>, Vec<Shape>) {
    let shapes = vec![
        Shape::Floor { z: 0.0 },
        // Two walls of the cell, so that every pixel sees something within 3 m.
        Shape::Box {
            lo: [-1.6, -2.5, 0.0],
            hi: [-1.5, 2.5, 2.6],
        },
        Shape::Box {
            lo: [-2.5, 1.5, 0.0],
            hi: [2.5, 1.6, 2.6],
        },
        // A table, a shelf, a cabinet and clutter.
        Shape::Box {
            lo: [-0.6, -0.4, 0.0],
            hi: [0.6, 0.4, 0.75],
        },
        Shape::Box {
            lo: [-1.5, 0.8, 0.0],
            hi: [-1.0, 1.5, 1.8],
        },
        Shape::Box {
            lo: [0.6, 0.9, 0.0],
            hi: [1.3, 1.5, 1.1],
        },
        Shape::Sphere {
            center: [0.0, 0.0, 1.0],
            radius: 0.25,
        },
        Shape::Sphere {
            center: [0.3, -0.5, 1.4],
            radius: 0.12,
        },
        Shape::Sphere {
            center: [-0.5, 0.6, 1.2],
            radius: 0.18,
        },
    ];
    let pose = look_at([0.7, -0.7, 1.9], [-0.8, 0.8, 0.5], [0.0, 0.0, 1.0]);
    (PinholeCamera::kinect_v2(3.0), pose, shapes)
}

/// A multi-line spinning lidar (VLP-16-like by default): `rings` beams spread evenly
/// over `vertical_fov` (radians, centred on the horizon), each sampled at
/// `azimuth_steps` angles over 360°.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Lidar {
    /// Number of beams (scan lines).
    pub rings: usize,
    /// Samples per beam over 360°.
    pub azimuth_steps: usize,
    /// Vertical field of view, radians, centred on the horizon.
    pub vertical_fov: f64,
    /// Longest range reported, metres.
    pub max_range: f64,
    /// Standard deviation of the range noise, metres.
    pub noise_sigma: f64,
}

impl Lidar {
    /// Velodyne VLP-16: 16 rings over 30°, ~15k points per turn, 100 m, σ ≈ 1.5 cm.
    pub fn vlp16() -> Self {
        Lidar {
            rings: 16,
            azimuth_steps: 940,
            vertical_fov: 30f64.to_radians(),
            max_range: 100.0,
            noise_sigma: 0.015,
        }
    }
}

/// One lidar turn at `base_from_sensor` against `shapes` (a box around the sensor acts
/// as the room): points in the sensor frame, ring by ring; beams that hit nothing
/// within range give no point. Range noise is Gaussian, reproducible from `seed`.
pub fn lidar_scan(
    lidar: &Lidar,
    base_from_sensor: &Matrix4<f64>,
    shapes: &[Shape],
    seed: u64,
) -> Vec<[f64; 3]> {
    let rot = base_from_sensor.fixed_view::<3, 3>(0, 0).into_owned();
    let o = Point3::from(base_from_sensor.fixed_view::<3, 1>(0, 3).into_owned());
    let mut rng = Rng::new(seed);
    let mut out = Vec::with_capacity(lidar.rings * lidar.azimuth_steps);
    for ring in 0..lidar.rings {
        let elevation = if lidar.rings > 1 {
            -lidar.vertical_fov / 2.0 + lidar.vertical_fov * ring as f64 / (lidar.rings - 1) as f64
        } else {
            0.0
        };
        for step in 0..lidar.azimuth_steps {
            let azimuth = std::f64::consts::TAU * step as f64 / lidar.azimuth_steps as f64;
            let local = Vector3::new(
                elevation.cos() * azimuth.cos(),
                elevation.cos() * azimuth.sin(),
                elevation.sin(),
            );
            let d = rot * local;
            let t = shapes
                .iter()
                .filter_map(|s| s.intersect(&o, &d))
                .fold(f64::INFINITY, f64::min);
            if t <= lidar.max_range {
                let r = t + lidar.noise_sigma * rng.normal();
                out.push([local.x * r, local.y * r, local.z * r]);
            }
        }
    }
    out
}

/// Occupied cell centres of a robot work cell at `resolution` (for the collision
/// benchmarks): the robot's base at the origin on a 3.6 m square floor just below
/// z = 0, two walls, an overhead camera rig plate at 1.6 m, a shelf, random boxes and a
/// person standing 0.7 m away with an arm reaching in. About 20k cells at 5 cm.
pub fn robot_cell_voxels(resolution: f64, seed: u64) -> Vec<[f64; 3]> {
    let mut rng = Rng::new(seed);
    let mut cells = std::collections::BTreeSet::new();
    let cell = |x: f64| (x / resolution).floor() as i64;
    let mut fill = |lo: [f64; 3], hi: [f64; 3], keep: &dyn Fn([f64; 3]) -> bool| {
        for i in cell(lo[0])..=cell(hi[0]) {
            for j in cell(lo[1])..=cell(hi[1]) {
                for k in cell(lo[2])..=cell(hi[2]) {
                    let c = [i, j, k].map(|g| (g as f64 + 0.5) * resolution);
                    if keep(c) {
                        cells.insert((i, j, k));
                    }
                }
            }
        }
    };
    let all = |_: [f64; 3]| true;
    let e = 0.5 * resolution;
    fill([-1.8, -1.8, -e], [1.8, 1.8, -e], &all); // floor
    fill([-1.8, -1.8, 0.0], [-1.8, 1.8, 1.6], &all); // back wall
    fill([-1.8, 1.8, 0.0], [1.8, 1.8, 1.6], &all); // side wall
    fill([-1.8, -1.8, 1.6], [1.8, 1.8, 1.6], &all); // camera rig plate
    for z in [0.3, 0.7, 1.1] {
        fill([0.9, -1.2, z], [1.3, -0.4, z], &all); // shelf boards
    }
    for _ in 0..8 {
        let size = [
            rng.uniform(0.15, 0.35),
            rng.uniform(0.15, 0.35),
            rng.uniform(0.15, 0.35),
        ];
        let angle = rng.uniform(0.0, std::f64::consts::TAU);
        let dist = rng.uniform(0.6, 1.5);
        let (cx, cy) = (dist * angle.cos(), dist * angle.sin());
        fill(
            [cx - size[0] / 2.0, cy - size[1] / 2.0, 0.0],
            [cx + size[0] / 2.0, cy + size[1] / 2.0, size[2]],
            &all,
        );
    }
    // A person: torso and head upright at (0.7, 0.6), an arm reaching toward the robot.
    let capsule = |a: [f64; 3], b: [f64; 3], r: f64| {
        move |p: [f64; 3]| crate::robot::point_segment_distance_squared(&a, &b, &p) <= r * r
    };
    let torso = capsule([0.9, 0.9, 0.9], [0.9, 0.9, 1.4], 0.17);
    fill([0.7, 0.7, 0.7], [1.1, 1.1, 1.6], &torso);
    let arm = capsule([0.8, 0.75, 1.3], [0.45, 0.35, 1.05], 0.05);
    fill([0.35, 0.25, 0.95], [0.9, 0.85, 1.4], &arm);
    cells
        .into_iter()
        .map(|(i, j, k)| [i, j, k].map(|g| (g as f64 + 0.5) * resolution))
        .collect()
}

/// Reproducible random numbers without a crate (xorshift64* + Box-Muller), for the
/// synthetic scenes and the tests.
pub struct Rng {
    state: u64,
    spare: Option<f64>,
}

impl Rng {
    /// A generator seeded with `seed` (every seed gives its own sequence).
    pub fn new(seed: u64) -> Self {
        Rng {
            state: seed.wrapping_mul(0x9E37_79B9_7F4A_7C15) | 1,
            spare: None,
        }
    }

    /// Uniform in (0, 1).
    pub fn unit(&mut self) -> f64 {
        self.state ^= self.state >> 12;
        self.state ^= self.state << 25;
        self.state ^= self.state >> 27;
        ((self.state.wrapping_mul(0x2545_F491_4F6C_DD1D) >> 11) as f64 + 0.5) / (1u64 << 53) as f64
    }

    /// Uniform in (lo, hi).
    pub fn uniform(&mut self, lo: f64, hi: f64) -> f64 {
        lo + (hi - lo) * self.unit()
    }

    /// Standard normal.
    pub fn normal(&mut self) -> f64 {
        if let Some(s) = self.spare.take() {
            return s;
        }
        let (u, v) = (self.unit(), self.unit());
        let r = (-2.0 * u.ln()).sqrt();
        let (s, c) = (std::f64::consts::TAU * v).sin_cos();
        self.spare = Some(r * s);
        r * c
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn lidar_in_an_empty_room_sees_its_walls() {
        let room = Shape::Box {
            lo: [-4.0, -4.0, 0.0],
            hi: [4.0, 4.0, 3.5],
        };
        let mut lidar = Lidar::vlp16();
        lidar.noise_sigma = 0.0;
        let pose = look_at([0.5, -1.0, 1.2], [2.0, -1.0, 1.2], [0.0, 0.0, 1.0]);
        let pts = lidar_scan(&lidar, &pose, &[room], 1);
        assert_eq!(
            pts.len(),
            16 * 940,
            "every beam hits a wall, the floor or the ceiling"
        );
        let rot = pose.fixed_view::<3, 3>(0, 0).into_owned();
        let o = pose.fixed_view::<3, 1>(0, 3).into_owned();
        for p in pts {
            let w = rot * Vector3::from(p) + o;
            let to_wall = [w.x + 4.0, 4.0 - w.x, w.y + 4.0, 4.0 - w.y, w.z, 3.5 - w.z]
                .into_iter()
                .fold(f64::INFINITY, f64::min);
            assert!(to_wall.abs() < 1e-9, "{w:?}");
        }
        // Noise: reproducible and of the requested spread.
        lidar.noise_sigma = 0.02;
        let a = lidar_scan(&lidar, &pose, &[room], 7);
        assert_eq!(a, lidar_scan(&lidar, &pose, &[room], 7));
        let mut g = Rng::new(3);
        let n = 20000;
        let samples: Vec<f64> = (0..n).map(|_| g.normal()).collect();
        let mean = samples.iter().sum::<f64>() / n as f64;
        let var = samples.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / n as f64;
        assert!(
            mean.abs() < 0.03 && (var.sqrt() - 1.0).abs() < 0.03,
            "{mean} {var}"
        );
    }

    #[test]
    fn sphere_points_lie_on_the_sphere() {
        let cam = PinholeCamera {
            width: 64,
            height: 48,
            fx: 60.0,
            fy: 60.0,
            cx: 32.0,
            cy: 24.0,
            max_depth: 10.0,
        };
        let pose = look_at([0.0, -3.0, 0.0], [0.0, 0.0, 0.0], [0.0, 0.0, 1.0]);
        let pts = render_points(
            &cam,
            &pose,
            &[Shape::Sphere {
                center: [0.0; 3],
                radius: 0.7,
            }],
        );
        assert!(!pts.is_empty());
        for p in pts {
            let r = (p[0] * p[0] + p[1] * p[1] + p[2] * p[2]).sqrt();
            assert!((r - 0.7).abs() < 1e-9);
            assert!(p[1] < 0.0, "only the near side is visible");
        }
    }
}
