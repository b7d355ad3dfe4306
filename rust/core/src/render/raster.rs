//! The z-buffer rasterizer. Triangles are clipped against the near plane in the camera
//! frame, projected with a pinhole, and filled pixel by pixel with edge functions; the
//! inverse depth is interpolated linearly in the image (which is exact for a plane
//! seen in perspective), so depth is the surface's own along each pixel's ray.

use crate::geometry::{cross, dot, sub};
use crate::{Error, Result};

/// The largest image drawn (64 Mpx: about 2 GB of buffers while drawing).
const MAX_PIXELS: usize = 1 << 26;

/// A triangle mesh in its own frame, with one colour and one label (what a
/// segmentation image reports for its pixels).
#[derive(Debug, Clone)]
pub struct Mesh {
    /// Vertex positions (m).
    pub vertices: Vec<[f64; 3]>,
    /// Vertex indices of each triangle.
    pub triangles: Vec<[u32; 3]>,
    /// Linear RGB in [0, 1].
    pub rgb: [f64; 3],
    /// The label written where the mesh is the nearest surface.
    pub label: i64,
}

/// A pinhole camera: OpenCV's convention (z forward, y down, pixel (u, v) centred at
/// (u, v)), depth accepted between `near` and `far`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Pinhole {
    /// Focal length in pixels, x.
    pub fx: f64,
    /// Focal length in pixels, y.
    pub fy: f64,
    /// Principal point, x (pixels).
    pub cx: f64,
    /// Principal point, y (pixels).
    pub cy: f64,
    /// Image width (pixels).
    pub width: usize,
    /// Image height (pixels).
    pub height: usize,
    /// Nearest depth drawn (m).
    pub near: f64,
    /// Farthest depth drawn (m).
    pub far: f64,
}

/// Lambertian shading with an ambient term: a surface facing the light (either side)
/// gets `ambient + diffuse` of its colour, one seen edge-on `ambient`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Light {
    /// Direction towards the light, in the camera frame (need not be unit length).
    pub direction: [f64; 3],
    /// Fraction of the colour every lit or unlit surface shows.
    pub ambient: f64,
    /// Fraction added in proportion to the cosine of the light's incidence.
    pub diffuse: f64,
}

/// A rendered frame, row-major.
#[derive(Debug, Clone)]
pub struct Render {
    /// RGB bytes, height × width × 3 (the background colour where nothing was drawn).
    pub rgb: Vec<u8>,
    /// Depth along the optical axis (m), 0 where nothing was drawn.
    pub depth: Vec<f64>,
    /// The nearest mesh's label, -1 where nothing was drawn.
    pub label: Vec<i64>,
}

/// Meshes held once, drawn many times from any camera with any poses.
#[derive(Debug, Clone, Default)]
pub struct Rasterizer {
    meshes: Vec<Mesh>,
}

impl Pinhole {
    /// Image position (x, y) and inverse depth of a camera-frame point in front.
    fn project(&self, p: [f64; 3]) -> [f64; 3] {
        [
            self.fx * p[0] / p[2] + self.cx,
            self.fy * p[1] / p[2] + self.cy,
            1.0 / p[2],
        ]
    }

    /// The pixel-centre box a projected triangle's bounds cover (empty: lo > hi).
    fn pixel_box(&self, v: &[[f64; 3]; 3]) -> ([f64; 2], [f64; 2]) {
        let lo_x = v[0][0].min(v[1][0]).min(v[2][0]).ceil().max(0.0);
        let hi_x = v[0][0]
            .max(v[1][0])
            .max(v[2][0])
            .floor()
            .min((self.width - 1) as f64);
        let lo_y = v[0][1].min(v[1][1]).min(v[2][1]).ceil().max(0.0);
        let hi_y = v[0][1]
            .max(v[1][1])
            .max(v[2][1])
            .floor()
            .min((self.height - 1) as f64);
        ([lo_x, lo_y], [hi_x, hi_y])
    }

    fn covers_a_pixel(&self, v: &[[f64; 3]; 3]) -> bool {
        let (lo, hi) = self.pixel_box(v);
        lo[0] <= hi[0] && lo[1] <= hi[1]
    }

    fn validate(&self) -> Result<()> {
        let finite = [self.fx, self.fy, self.cx, self.cy, self.near, self.far]
            .iter()
            .all(|v| v.is_finite());
        if !finite || self.fx <= 0.0 || self.fy <= 0.0 {
            return Err(Error::InvalidArgument(format!(
                "the camera's focal lengths must be positive and its parameters finite, got fx={} fy={} cx={} cy={}",
                self.fx, self.fy, self.cx, self.cy
            )));
        }
        if !(self.near > 0.0 && self.far > self.near) {
            return Err(Error::InvalidArgument(format!(
                "the camera needs 0 < near < far, got near={} far={}",
                self.near, self.far
            )));
        }
        if self.width == 0
            || self.height == 0
            || self.width.saturating_mul(self.height) > MAX_PIXELS
        {
            return Err(Error::InvalidArgument(format!(
                "the image must have 1 to {MAX_PIXELS} pixels, got {}×{}",
                self.width, self.height
            )));
        }
        Ok(())
    }
}

impl Rasterizer {
    /// An empty scene.
    pub fn new() -> Self {
        Self::default()
    }

    /// Adds a mesh and returns its index (the order poses are given in [`Self::render`]).
    pub fn add_mesh(&mut self, mesh: Mesh) -> Result<usize> {
        let n = mesh.vertices.len();
        if let Some(t) = mesh
            .triangles
            .iter()
            .find(|t| t.iter().any(|&i| i as usize >= n))
        {
            return Err(Error::InvalidArgument(format!(
                "triangle {t:?} names a vertex beyond the mesh's {n} vertices"
            )));
        }
        if mesh.vertices.iter().flatten().any(|v| !v.is_finite()) {
            return Err(Error::InvalidArgument(
                "mesh vertices must be finite".into(),
            ));
        }
        if mesh.rgb.iter().any(|c| !(0.0..=1.0).contains(c)) {
            return Err(Error::InvalidArgument(format!(
                "mesh colour must lie in [0, 1], got {:?}",
                mesh.rgb
            )));
        }
        self.meshes.push(mesh);
        Ok(self.meshes.len() - 1)
    }

    /// The number of meshes held.
    pub fn len(&self) -> usize {
        self.meshes.len()
    }

    /// Whether no mesh is held.
    pub fn is_empty(&self) -> bool {
        self.meshes.is_empty()
    }

    /// Draws every mesh placed by `camera_from_mesh` (row-major 4×4, one per mesh; a
    /// mesh whose pose is `None` is skipped) into a `camera`-sized frame, shaded by
    /// `light`; `background` fills the colour where nothing is drawn.
    pub fn render(
        &self,
        camera_from_mesh: &[Option<[[f64; 4]; 4]>],
        camera: &Pinhole,
        light: &Light,
        background: [u8; 3],
    ) -> Result<Render> {
        camera.validate()?;
        if camera_from_mesh.len() != self.meshes.len() {
            return Err(Error::InvalidArgument(format!(
                "{} poses given for {} meshes",
                camera_from_mesh.len(),
                self.meshes.len()
            )));
        }
        let lnorm = light.direction.iter().map(|v| v * v).sum::<f64>().sqrt();
        if !(lnorm > 0.0
            && lnorm.is_finite()
            && light.ambient.is_finite()
            && light.diffuse.is_finite())
        {
            return Err(Error::InvalidArgument(
                "the light needs a finite, non-zero direction".into(),
            ));
        }
        let towards_light = light.direction.map(|v| v / lnorm);
        let (w, h) = (camera.width, camera.height);
        let mut frame = Frame {
            camera,
            inv_depth: vec![0.0; w * h],
            shade: vec![[0; 3]; w * h],
            label: vec![-1; w * h],
        };
        let mut placed: Vec<[f64; 3]> = Vec::new();
        let mut projected: Vec<[f64; 3]> = Vec::new();
        for (mesh, pose) in self.meshes.iter().zip(camera_from_mesh) {
            let Some(m) = pose else { continue };
            if m.iter().flatten().any(|v| !v.is_finite()) {
                return Err(Error::InvalidArgument("mesh poses must be finite".into()));
            }
            placed.clear();
            placed.extend(mesh.vertices.iter().map(|p| {
                let r = |i: usize| m[i][0] * p[0] + m[i][1] * p[1] + m[i][2] * p[2] + m[i][3];
                [r(0), r(1), r(2)]
            }));
            projected.clear();
            projected.extend(placed.iter().map(|&p| camera.project(p)));
            for t in &mesh.triangles {
                let [a, b, c] = t.map(|i| i as usize);
                let tri = [placed[a], placed[b], placed[c]];
                let in_front = tri.iter().all(|p| p[2] >= camera.near);
                // Most of a detailed mesh's triangles fall between pixel centres: skip
                // them before shading.
                if in_front && !camera.covers_a_pixel(&[projected[a], projected[b], projected[c]]) {
                    continue;
                }
                let normal = cross(&sub(&tri[1], &tri[0]), &sub(&tri[2], &tri[0]));
                let len = dot(&normal, &normal).sqrt();
                if len.is_nan() || len <= 0.0 {
                    continue;
                }
                let cosine = (dot(&normal, &towards_light) / len).abs();
                let gain = (light.ambient + light.diffuse * cosine).clamp(0.0, 1.0);
                let colour = mesh
                    .rgb
                    .map(|c| (c * gain * 255.0).round().clamp(0.0, 255.0) as u8);
                if in_front {
                    frame.draw(
                        [projected[a], projected[b], projected[c]],
                        colour,
                        mesh.label,
                    );
                } else {
                    frame.draw_clipped(tri, colour, mesh.label);
                }
            }
        }
        Ok(frame.finish(background))
    }
}

/// The z-buffer while drawing: inverse depth (0 = empty), colour and label.
struct Frame<'a> {
    camera: &'a Pinhole,
    inv_depth: Vec<f64>,
    shade: Vec<[u8; 3]>,
    label: Vec<i64>,
}

impl Frame<'_> {
    /// Clips a camera-frame triangle to z ≥ near (a polygon of up to four vertices)
    /// and draws it as a fan.
    fn draw_clipped(&mut self, tri: [[f64; 3]; 3], shade: [u8; 3], label: i64) {
        let near = self.camera.near;
        if tri.iter().all(|p| p[2] < near) || tri.iter().all(|p| p[2] > self.camera.far) {
            return;
        }
        let mut poly = [[0.0; 3]; 4];
        let mut n = 0;
        for i in 0..3 {
            let (a, b) = (tri[i], tri[(i + 1) % 3]);
            if a[2] >= near {
                poly[n] = a;
                n += 1;
            }
            if (a[2] >= near) != (b[2] >= near) {
                let t = (near - a[2]) / (b[2] - a[2]);
                poly[n] = [a[0] + t * (b[0] - a[0]), a[1] + t * (b[1] - a[1]), near];
                n += 1;
            }
        }
        let c = self.camera;
        for k in 1..n.saturating_sub(1) {
            self.draw(
                [
                    c.project(poly[0]),
                    c.project(poly[k]),
                    c.project(poly[k + 1]),
                ],
                shade,
                label,
            );
        }
    }

    /// Fills the pixels whose centres lie inside the projected triangle (x, y, 1/z
    /// per corner; edges included), keeping the nearest surface.
    fn draw(&mut self, projected: [[f64; 3]; 3], shade: [u8; 3], label: i64) {
        let c = self.camera;
        let [a, b, d] = projected;
        let area = (b[0] - a[0]) * (d[1] - a[1]) - (b[1] - a[1]) * (d[0] - a[0]);
        if area.is_nan() || area.abs() <= 1e-12 {
            return;
        }
        let ([lo_x, lo_y], [hi_x, hi_y]) = c.pixel_box(&projected);
        if lo_x > hi_x || lo_y > hi_y {
            return;
        }
        let inv_area = 1.0 / area;
        // Barycentric weights as affine functions of the pixel: w_i = e_i(x, y) / area,
        // e_i(x, y) = A_i x + B_i y + C_i (the edge opposite vertex i).
        let edge = |p: [f64; 3], q: [f64; 3]| {
            let ea = (p[1] - q[1]) * inv_area;
            let eb = (q[0] - p[0]) * inv_area;
            let ec = (p[0] * q[1] - p[1] * q[0]) * inv_area;
            (ea, eb, ec)
        };
        let e = [edge(b, d), edge(d, a), edge(a, b)];
        // 1/z is affine in the image: its gradient from the weights.
        let (za, zb, zc) = (
            e[0].0 * a[2] + e[1].0 * b[2] + e[2].0 * d[2],
            e[0].1 * a[2] + e[1].1 * b[2] + e[2].1 * d[2],
            e[0].2 * a[2] + e[1].2 * b[2] + e[2].2 * d[2],
        );
        let (max_inv, min_inv) = (1.0 / c.near, 1.0 / c.far);
        // Pixels on an edge are filled by both triangles sharing it (the z-test keeps one).
        let tol = -1e-9;
        let width = c.width;
        for y in lo_y as usize..=hi_y as usize {
            let yf = y as f64;
            let row = [
                e[0].1 * yf + e[0].2,
                e[1].1 * yf + e[1].2,
                e[2].1 * yf + e[2].2,
            ];
            // The span of x where all three weights are ≥ 0, solved per edge.
            let (mut x0, mut x1) = (lo_x, hi_x);
            let mut empty = false;
            for (i, (ea, _, _)) in e.iter().enumerate() {
                if *ea > 0.0 {
                    x0 = x0.max(((tol - row[i]) / ea).ceil());
                } else if *ea < 0.0 {
                    x1 = x1.min(((tol - row[i]) / ea).floor());
                } else if row[i] < tol {
                    empty = true;
                }
            }
            if empty || x0 > x1 {
                continue;
            }
            let base = y * width;
            let zrow = zb * yf + zc;
            for x in x0 as usize..=x1 as usize {
                let inv = za * x as f64 + zrow;
                if !(min_inv..=max_inv).contains(&inv) {
                    continue;
                }
                let i = base + x;
                if inv > self.inv_depth[i] {
                    self.inv_depth[i] = inv;
                    self.shade[i] = shade;
                    self.label[i] = label;
                }
            }
        }
    }

    fn finish(self, background: [u8; 3]) -> Render {
        let mut rgb = Vec::with_capacity(3 * self.inv_depth.len());
        let mut depth = Vec::with_capacity(self.inv_depth.len());
        for (inv, shade) in self.inv_depth.iter().zip(&self.shade) {
            if *inv > 0.0 {
                rgb.extend_from_slice(shade);
                depth.push(1.0 / inv);
            } else {
                rgb.extend_from_slice(&background);
                depth.push(0.0);
            }
        }
        Render {
            rgb,
            depth,
            label: self.label,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const IDENTITY: [[f64; 4]; 4] = [
        [1.0, 0.0, 0.0, 0.0],
        [0.0, 1.0, 0.0, 0.0],
        [0.0, 0.0, 1.0, 0.0],
        [0.0, 0.0, 0.0, 1.0],
    ];

    fn camera() -> Pinhole {
        Pinhole {
            fx: 100.0,
            fy: 120.0,
            cx: 31.5,
            cy: 23.5,
            width: 64,
            height: 48,
            near: 0.1,
            far: 10.0,
        }
    }

    fn light() -> Light {
        Light {
            direction: [0.0, 0.0, -1.0],
            ambient: 0.5,
            diffuse: 0.5,
        }
    }

    /// A square in a tilted plane, two triangles.
    fn tilted_square(label: i64) -> (Mesh, [f64; 4]) {
        // Plane n·p = d with n = (0.2, -0.1, 1) normalised-free: z = 2 - 0.2 x + 0.1 y.
        let z = |x: f64, y: f64| 2.0 - 0.2 * x + 0.1 * y;
        let corners = [[-1.0, -1.0], [1.0, -1.0], [1.0, 1.0], [-1.0, 1.0]];
        let vertices = corners
            .iter()
            .map(|c| [c[0], c[1], z(c[0], c[1])])
            .collect();
        (
            Mesh {
                vertices,
                triangles: vec![[0, 1, 2], [0, 2, 3]],
                rgb: [1.0, 0.5, 0.25],
                label,
            },
            [0.2, -0.1, 1.0, 2.0],
        )
    }

    #[test]
    fn plane_depth_is_exact_along_each_ray() {
        let mut r = Rasterizer::new();
        let (mesh, plane) = tilted_square(7);
        r.add_mesh(mesh).unwrap();
        let cam = camera();
        let out = r
            .render(&[Some(IDENTITY)], &cam, &light(), [0, 0, 0])
            .unwrap();
        let mut hits = 0;
        for v in 0..cam.height {
            for u in 0..cam.width {
                let i = v * cam.width + u;
                let (x, y) = ((u as f64 - cam.cx) / cam.fx, (v as f64 - cam.cy) / cam.fy);
                // The ray (x, y, 1) t meets a x + b y + z = d at t = d / (a x + b y + 1).
                let t = plane[3] / (plane[0] * x + plane[1] * y + plane[2]);
                let (px, py) = (x * t, y * t);
                let inside = px.abs() < 1.0 - 1e-6 && py.abs() < 1.0 - 1e-6;
                let outside = px.abs() > 1.0 + 1e-6 || py.abs() > 1.0 + 1e-6;
                if inside {
                    hits += 1;
                    assert!(
                        (out.depth[i] - t).abs() < 1e-9,
                        "pixel ({u}, {v}): {} vs {t}",
                        out.depth[i]
                    );
                    assert_eq!(out.label[i], 7);
                } else if outside {
                    assert_eq!(out.depth[i], 0.0);
                    assert_eq!(out.label[i], -1);
                }
            }
        }
        assert!(hits > 1000, "{hits}");
    }

    #[test]
    fn nearer_surface_wins_and_shading_follows_the_light() {
        let mut r = Rasterizer::new();
        let quad = |z: f64, label: i64| Mesh {
            vertices: vec![
                [-5.0, -5.0, z],
                [5.0, -5.0, z],
                [5.0, 5.0, z],
                [-5.0, 5.0, z],
            ],
            triangles: vec![[0, 1, 2], [0, 2, 3]],
            rgb: [0.8, 0.4, 0.2],
            label,
        };
        r.add_mesh(quad(3.0, 1)).unwrap();
        r.add_mesh(quad(2.0, 2)).unwrap();
        let cam = camera();
        let out = r
            .render(&[Some(IDENTITY), Some(IDENTITY)], &cam, &light(), [9, 9, 9])
            .unwrap();
        assert!(out.label.iter().all(|&l| l == 2));
        assert!(out.depth.iter().all(|&d| (d - 2.0).abs() < 1e-12));
        // Facing the light: ambient + diffuse = 1.
        assert_eq!(&out.rgb[..3], &[204, 102, 51]);
        // Skipping the near one shows the far one; a pose moves it.
        let mut moved = IDENTITY;
        moved[2][3] = 1.5;
        let out = r
            .render(&[Some(moved), None], &cam, &light(), [9, 9, 9])
            .unwrap();
        assert!(out.label.iter().all(|&l| l == 1));
        assert!(out.depth.iter().all(|&d| (d - 4.5).abs() < 1e-12));
    }

    #[test]
    fn triangles_behind_the_camera_are_clipped_not_mirrored() {
        // A floor from behind the camera to far in front: only z ≥ near is drawn, and
        // every drawn depth is on the floor's ray intersection.
        let mut r = Rasterizer::new();
        let y = 0.5;
        r.add_mesh(Mesh {
            vertices: vec![
                [-20.0, y, -5.0],
                [20.0, y, -5.0],
                [20.0, y, 8.0],
                [-20.0, y, 8.0],
            ],
            triangles: vec![[0, 1, 2], [0, 2, 3]],
            rgb: [0.5, 0.5, 0.5],
            label: 3,
        })
        .unwrap();
        let cam = camera();
        let out = r
            .render(&[Some(IDENTITY)], &cam, &light(), [0, 0, 0])
            .unwrap();
        for v in 0..cam.height {
            for u in 0..cam.width {
                let i = v * cam.width + u;
                let ray_y = (v as f64 - cam.cy) / cam.fy;
                if ray_y > 0.0 && y / ray_y < 8.0 - 1e-6 && y / ray_y >= cam.near {
                    assert!((out.depth[i] - y / ray_y).abs() < 1e-9);
                } else if ray_y <= 0.0 || y / ray_y > 8.0 + 1e-6 {
                    assert_eq!(
                        out.depth[i], 0.0,
                        "pixel ({u}, {v}) looks up or beyond the floor's end"
                    );
                }
            }
        }
    }

    #[test]
    fn bad_input_is_refused() {
        let mut r = Rasterizer::new();
        let bad = Mesh {
            vertices: vec![[0.0; 3]],
            triangles: vec![[0, 1, 2]],
            rgb: [0.0; 3],
            label: 0,
        };
        assert!(r.add_mesh(bad).is_err());
        let (mesh, _) = tilted_square(1);
        r.add_mesh(mesh).unwrap();
        assert!(r.render(&[], &camera(), &light(), [0; 3]).is_err());
        let mut cam = camera();
        cam.near = 0.0;
        assert!(r.render(&[Some(IDENTITY)], &cam, &light(), [0; 3]).is_err());
        let dark = Light {
            direction: [0.0; 3],
            ambient: 0.5,
            diffuse: 0.5,
        };
        assert!(r
            .render(&[Some(IDENTITY)], &camera(), &dark, [0; 3])
            .is_err());
    }
}
