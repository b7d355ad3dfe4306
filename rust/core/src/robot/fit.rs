//! A capsule or cylinder that encloses a link's mesh vertices: for a few candidate
//! axes (the vertices' principal axes and the link frame's axes) the smallest
//! enclosing circle of the vertices projected across the axis gives the radius and
//! the axis line; a capsule's ends are pulled in as far as its rounded caps allow, a
//! cylinder's end planes touch the extreme vertices; the smallest body by volume wins.

use crate::error::{Error, Result};
use crate::na::{Matrix3, Vector2, Vector3};
use crate::robot::body::Body;
use crate::robot::capsule::Capsule;

/// Relative growth that keeps vertices lying exactly on the fitted surface inside it
/// despite rounding in the change of basis.
const ROUNDING_SLACK: f64 = 1e-12;

/// Which body shapes `fit_body` may choose.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum FitShape {
    /// Always a capsule.
    Capsule,
    /// Always a cylinder.
    Cylinder,
    /// Whichever encloses the vertices with less volume.
    Auto,
}

/// Smallest body of the allowed shapes (among the candidate axes) containing every
/// vertex, then grown by `padding` in every direction.
pub fn fit_body(vertices: &[[f64; 3]], padding: f64, shape: FitShape) -> Result<Body> {
    let capsule = || fit_capsule(vertices, padding).map(|c| Body::capsule(c.a, c.b, c.radius));
    match shape {
        FitShape::Capsule => capsule(),
        FitShape::Cylinder => fit_cylinder(vertices, padding),
        FitShape::Auto => {
            let (a, b) = (capsule()?, fit_cylinder(vertices, padding)?);
            Ok(if b.volume() < a.volume() { b } else { a })
        }
    }
}

/// Smallest cylinder (among the candidate axes) containing every vertex, grown by
/// `padding` in radius and at both ends.
pub fn fit_cylinder(vertices: &[[f64; 3]], padding: f64) -> Result<Body> {
    let axes = candidate_axes(vertices, padding)?;
    // Flat cylinders tie at volume zero: vertices on a segment fit both a cylinder
    // along it (radius 0) and a disc across it (length 0). Comparing volumes grown by
    // a sliver of the vertices' extent breaks such ties by surface, then by length
    // (Steiner's formula), and leaves the order of bodies of real volume unchanged.
    let sliver = 1e-6 * bounding_extent(vertices);
    let grown_volume = |b: &Body| {
        let r = b.radius() + sliver;
        std::f64::consts::PI * r * r * (b.axis.length() + 2.0 * sliver)
    };
    let mut best: Option<Body> = None;
    for axis in axes {
        let (u, w) = across_basis(&axis);
        let across: Vec<Vector2<f64>> = vertices
            .iter()
            .map(|v| Vector2::new(u.dot(&Vector3::from(*v)), w.dot(&Vector3::from(*v))))
            .collect();
        let (centre, _) = smallest_enclosing_circle(&across);
        let radius = across
            .iter()
            .map(|p| (p - centre).norm())
            .fold(0.0, f64::max);
        let (lo, hi) = vertices
            .iter()
            .fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), v| {
                let t = axis.dot(&Vector3::from(*v));
                (lo.min(t), hi.max(t))
            });
        let on_axis = |t: f64| {
            let p = u * centre.x + w * centre.y + axis * t;
            [p.x, p.y, p.z]
        };
        // Vertices on the fitted surface stay inside despite the change of basis.
        let slack = ROUNDING_SLACK * (1.0 + radius + lo.abs().max(hi.abs()));
        let body = Body::cylinder(
            on_axis(lo - padding - slack),
            on_axis(hi + padding + slack),
            radius + padding + slack,
        );
        if best.is_none_or(|b| grown_volume(&body) < grown_volume(&b)) {
            best = Some(body);
        }
    }
    best.ok_or_else(|| Error::InvalidArgument("no cylinder fitted".into()))
}

/// The longest edge of the vertices' axis-aligned bounding box.
fn bounding_extent(vertices: &[[f64; 3]]) -> f64 {
    (0..3)
        .map(|a| {
            let (lo, hi) = vertices
                .iter()
                .fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), v| {
                    (lo.min(v[a]), hi.max(v[a]))
                });
            hi - lo
        })
        .fold(0.0, f64::max)
}

/// Check the inputs; the link axes and the vertices' principal axes.
fn candidate_axes(vertices: &[[f64; 3]], padding: f64) -> Result<Vec<Vector3<f64>>> {
    if vertices.is_empty() {
        return Err(Error::InvalidArgument(
            "cannot fit a body to no vertices".into(),
        ));
    }
    crate::geometry::check_finite(vertices, "vertex")?;
    if !(padding.is_finite() && padding >= 0.0) {
        return Err(Error::InvalidArgument(format!(
            "padding must be finite and ≥ 0, got {}",
            crate::geometry::fmt_num(padding)
        )));
    }
    let n = vertices.len() as f64;
    let mean = vertices
        .iter()
        .fold(Vector3::zeros(), |acc, v| acc + Vector3::from(*v))
        / n;
    let mut cov = Matrix3::zeros();
    for v in vertices {
        let d = Vector3::from(*v) - mean;
        cov += d * d.transpose();
    }
    let mut axes: Vec<Vector3<f64>> = vec![Vector3::x(), Vector3::y(), Vector3::z()];
    let eig = crate::na::SymmetricEigen::new(cov / n);
    for i in 0..3 {
        let v = eig.eigenvectors.column(i).into_owned();
        if v.norm() > 0.5 {
            axes.push(v.normalize());
        }
    }
    Ok(axes)
}

/// Smallest capsule (among the candidate axes) containing every vertex, then grown by
/// `padding`.
pub fn fit_capsule(vertices: &[[f64; 3]], padding: f64) -> Result<Capsule> {
    let axes = candidate_axes(vertices, padding)?;
    let mut best: Option<Capsule> = None;
    for axis in axes {
        let c = capsule_along(vertices, &axis);
        if best.is_none_or(|b| c.volume() < b.volume()) {
            best = Some(c);
        }
    }
    let mut capsule = best.ok_or_else(|| Error::InvalidArgument("no capsule fitted".into()))?;
    let extent = capsule
        .a
        .iter()
        .chain(&capsule.b)
        .fold(0.0f64, |m, v| m.max(v.abs()));
    capsule.radius += padding + ROUNDING_SLACK * (1.0 + capsule.radius + extent);
    Ok(capsule)
}

/// An orthonormal basis (u, w) across a unit axis.
fn across_basis(axis: &Vector3<f64>) -> (Vector3<f64>, Vector3<f64>) {
    let helper = if axis.x.abs() < 0.9 {
        Vector3::x()
    } else {
        Vector3::y()
    };
    let u = axis.cross(&helper).normalize();
    (u, axis.cross(&u))
}

/// Smallest capsule with its axis along `axis` that contains every vertex.
fn capsule_along(vertices: &[[f64; 3]], axis: &Vector3<f64>) -> Capsule {
    let (u, w) = across_basis(axis);
    let across: Vec<Vector2<f64>> = vertices
        .iter()
        .map(|v| {
            let v = Vector3::from(*v);
            Vector2::new(u.dot(&v), w.dot(&v))
        })
        .collect();
    let (centre, _) = smallest_enclosing_circle(&across);
    let radius = across
        .iter()
        .map(|p| (p - centre).norm())
        .fold(0.0, f64::max);
    // Pull each end in until a vertex would poke out of its cap.
    let (mut t_a, mut t_b) = (f64::INFINITY, f64::NEG_INFINITY);
    for (v, p) in vertices.iter().zip(&across) {
        let t = axis.dot(&Vector3::from(*v));
        let rho = (p - centre).norm();
        let s = (radius * radius - rho * rho).max(0.0).sqrt();
        t_a = t_a.min(t + s);
        t_b = t_b.max(t - s);
    }
    if t_a > t_b {
        // Short and wide: a sphere anywhere in [t_b, t_a] holds everything.
        let mid = 0.5 * (t_a + t_b);
        t_a = mid;
        t_b = mid;
    }
    let on_axis = |t: f64| {
        let p = u * centre.x + w * centre.y + axis * t;
        [p.x, p.y, p.z]
    };
    Capsule::new(on_axis(t_a), on_axis(t_b), radius)
}

/// Welzl's algorithm (iterative, move-to-front free): expected linear time on points
/// taken in a scrambled order.
fn smallest_enclosing_circle(points: &[Vector2<f64>]) -> (Vector2<f64>, f64) {
    // A fixed scramble (multiplicative hashing of the index) keeps results reproducible.
    let n = points.len();
    let mut order: Vec<usize> = (0..n).collect();
    order.sort_by_key(|&i| (i as u64).wrapping_mul(0x9E37_79B9_7F4A_7C15));
    let pts: Vec<Vector2<f64>> = order.iter().map(|&i| points[i]).collect();
    let inside =
        |c: &Vector2<f64>, r: f64, p: &Vector2<f64>| (p - c).norm() <= r * (1.0 + 1e-12) + 1e-15;
    let mut c = pts[0];
    let mut r = 0.0;
    for i in 1..n {
        if inside(&c, r, &pts[i]) {
            continue;
        }
        c = pts[i];
        r = 0.0;
        for j in 0..i {
            if inside(&c, r, &pts[j]) {
                continue;
            }
            c = (pts[i] + pts[j]) * 0.5;
            r = (pts[i] - c).norm();
            for k in 0..j {
                if inside(&c, r, &pts[k]) {
                    continue;
                }
                (c, r) = circle_through(&pts[i], &pts[j], &pts[k]);
            }
        }
    }
    (c, r)
}

/// Circumcircle of three points; for (nearly) collinear ones the circle on the farthest pair.
fn circle_through(a: &Vector2<f64>, b: &Vector2<f64>, c: &Vector2<f64>) -> (Vector2<f64>, f64) {
    let (ab, ac) = (b - a, c - a);
    let d = 2.0 * (ab.x * ac.y - ab.y * ac.x);
    if d.abs() < 1e-300 || d.abs() <= 1e-12 * ab.norm_squared().max(ac.norm_squared()) {
        let pairs = [(a, b), (a, c), (b, c)];
        let (p, q) = pairs
            .iter()
            .max_by(|x, y| (x.0 - x.1).norm().total_cmp(&(y.0 - y.1).norm()))
            .copied()
            .unwrap_or((a, b));
        let centre = (p + q) * 0.5;
        return (centre, (p - centre).norm());
    }
    let (ab2, ac2) = (ab.norm_squared(), ac.norm_squared());
    let ux = (ac.y * ab2 - ab.y * ac2) / d;
    let uy = (ab.x * ac2 - ac.x * ab2) / d;
    let centre = a + Vector2::new(ux, uy);
    (centre, (a - centre).norm())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::robot::body::BodyShape;
    use crate::synthetic::Rng;

    #[test]
    fn encloses_every_vertex_and_is_tight_for_a_cylinder() {
        // Vertices of a cylinder of radius 0.05 from z = 0 to 0.4, tilted.
        let mut pts = Vec::new();
        for i in 0..64 {
            let a = i as f64 / 64.0 * std::f64::consts::TAU;
            for z in [0.0, 0.4] {
                pts.push([0.05 * a.cos() + 0.3 * z, 0.05 * a.sin(), z]);
            }
        }
        let c = fit_capsule(&pts, 0.005).unwrap();
        assert!(pts.iter().all(|p| c.contains_point(p)));
        assert!((c.radius - 0.055).abs() < 2e-3, "{}", c.radius);
    }

    #[test]
    fn random_clouds_are_enclosed() {
        let mut rng = Rng::new(11);
        for _ in 0..50 {
            let scale = [
                rng.uniform(0.01, 0.5),
                rng.uniform(0.01, 0.5),
                rng.uniform(0.01, 0.5),
            ];
            let pts: Vec<[f64; 3]> = (0..300)
                .map(|_| {
                    [
                        rng.normal() * scale[0],
                        rng.normal() * scale[1],
                        rng.normal() * scale[2],
                    ]
                })
                .collect();
            let c = fit_capsule(&pts, 0.0).unwrap();
            for p in &pts {
                let d = crate::robot::capsule::point_segment_distance_squared(&c.a, &c.b, p).sqrt();
                assert!(d <= c.radius * (1.0 + 1e-9) + 1e-12);
            }
        }
    }

    #[test]
    fn cylinders_enclose_and_win_for_stubby_shapes() {
        let mut rng = Rng::new(5);
        // A squat can (radius 0.06, height 0.12): a cylinder fits it exactly.
        let mut pts = Vec::new();
        for _ in 0..2000 {
            let a = rng.uniform(0.0, std::f64::consts::TAU);
            let r = 0.06 * rng.unit().sqrt();
            pts.push([r * a.cos(), r * a.sin(), rng.uniform(-0.06, 0.06)]);
        }
        let body = fit_body(&pts, 0.005, FitShape::Auto).unwrap();
        assert_eq!(body.shape, BodyShape::Cylinder);
        assert!(pts.iter().all(|p| body.contains_point(p)));
        assert!(
            body.radius() < 0.066 && body.axis.length() < 0.131,
            "{body:?}"
        );
        // A long rod with rounded ends (points on a capsule's surface) prefers a capsule.
        let mut rod = Vec::new();
        for _ in 0..5000 {
            let (u, v, w) = (rng.normal(), rng.normal(), rng.normal());
            let n = (u * u + v * v + w * w).sqrt();
            let (u, v, w) = (0.04 * u / n, 0.04 * v / n, 0.04 * w / n);
            // Caps on the unit sphere's halves, the side on the circle.
            let z = if w < 0.0 { 0.04 + w } else { 0.96 + w };
            rod.push([u, v, z]);
            let a = rng.uniform(0.0, std::f64::consts::TAU);
            rod.push([0.04 * a.cos(), 0.04 * a.sin(), rng.uniform(0.04, 0.96)]);
        }
        let body = fit_body(&rod, 0.0, FitShape::Auto).unwrap();
        assert_eq!(body.shape, BodyShape::Capsule);
        assert!(rod.iter().all(|p| body.contains_point(p)));
    }

    #[test]
    fn vertices_on_a_segment_fit_the_segment_along_any_direction() {
        // The analytic answer: a cylinder (or capsule) of radius `padding` whose axis
        // is the segment, lengthened by `padding` at each end for the cylinder.
        let s = 1.0 / 3f64.sqrt();
        let directions = [
            [1.0, 0.0, 0.0],
            [0.0, 1.0, 0.0],
            [0.0, 0.0, 1.0],
            [0.0, 0.0, -1.0],
            [s, s, s],
            [0.6, 0.0, 0.8],
            [0.0, -0.28, 0.96],
        ];
        let start = [0.1, -0.2, 0.3];
        let length = 0.7;
        for d in directions {
            let at = |t: f64| [0, 1, 2].map(|i| start[i] + d[i] * t);
            let pts: Vec<[f64; 3]> = (0..=20).map(|i| at(length * f64::from(i) / 20.0)).collect();
            for padding in [0.0, 0.01] {
                let cyl = fit_cylinder(&pts, padding).unwrap();
                let (a, b) = (cyl.axis.a, cyl.axis.b);
                // Either orientation of the axis is the same cylinder.
                let (a, b) = if crate::geometry::distance_squared(&a, &at(-padding))
                    < crate::geometry::distance_squared(&b, &at(-padding))
                {
                    (a, b)
                } else {
                    (b, a)
                };
                let tol = 1e-9;
                assert!(
                    cyl.radius() >= padding && cyl.radius() < padding + tol,
                    "{d:?}: radius {}",
                    cyl.radius()
                );
                assert!(
                    crate::geometry::distance_squared(&a, &at(-padding)).sqrt() < tol,
                    "{d:?}: {a:?}"
                );
                assert!(
                    crate::geometry::distance_squared(&b, &at(length + padding)).sqrt() < tol,
                    "{d:?}: {b:?}"
                );
                assert!(pts.iter().all(|p| cyl.contains_point(p)));
                let cap = fit_capsule(&pts, padding).unwrap();
                assert!(
                    (cap.length() - length).abs() < tol,
                    "{d:?}: capsule length {}",
                    cap.length()
                );
                assert!(cap.radius >= padding && cap.radius < padding + tol);
                let auto = fit_body(&pts, padding, FitShape::Auto).unwrap();
                assert!(auto.radius() < padding + tol, "{d:?}: {auto:?}");
            }
        }
    }

    #[test]
    fn vertices_on_a_disc_fit_a_flat_cylinder() {
        // Points on a circle of radius 0.2 in the plane z = 0.5: a cylinder of radius
        // 0.2 and length 0 along z (the only body of zero volume).
        let pts: Vec<[f64; 3]> = (0..64)
            .map(|i| {
                let a = f64::from(i) / 64.0 * std::f64::consts::TAU;
                [0.2 * a.cos(), 0.2 * a.sin(), 0.5]
            })
            .collect();
        let cyl = fit_cylinder(&pts, 0.0).unwrap();
        assert!((cyl.radius() - 0.2).abs() < 1e-9, "{cyl:?}");
        assert!(cyl.axis.length() < 1e-9, "{cyl:?}");
        assert!((cyl.axis.a[2] - 0.5).abs() < 1e-9);
    }

    #[test]
    fn rejects_empty_and_nan() {
        assert!(fit_capsule(&[], 0.0).is_err());
        assert!(fit_capsule(&[[f64::NAN, 0.0, 0.0]], 0.0).is_err());
        assert!(fit_capsule(&[[0.0; 3]], -1.0).is_err());
    }
}
