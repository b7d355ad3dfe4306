//! Does a body meet an axis-aligned box? Closed form for both shapes: a capsule by
//! its axis' closest approach, a cylinder also by the disc at a flat end.

use parry3d_f64::na::Vector3;

use super::{Body, BodyShape};
use crate::robot::capsule::{point_segment_distance_squared, segment_box_closest};

impl Body {
    /// Does the body meet the axis-aligned box (touching counts)? Exact, in closed
    /// form: for cylinders the enclosing capsule's closest approach decides, unless it
    /// is at a flat end, where the end disc decides.
    pub fn overlaps_box(&self, center: &[f64; 3], half: &[f64; 3]) -> bool {
        let c = &self.axis;
        let r = c.radius;
        // Cheap answers from the box's centre: farther than r plus the half diagonal
        // from the axis cannot touch; a centre inside the body is an overlap.
        let reach = r + (half[0] * half[0] + half[1] * half[1] + half[2] * half[2]).sqrt();
        let centre_d2 = point_segment_distance_squared(&c.a, &c.b, center);
        if centre_d2 > reach * reach {
            return false;
        }
        let centre_inside = match self.shape {
            BodyShape::Capsule => centre_d2 <= r * r,
            BodyShape::Cylinder => self.contains_point(center),
        };
        if centre_inside {
            return true;
        }
        let (d2, t, q) = segment_box_closest(&c.a, &c.b, center, half);
        if d2 > r * r {
            return false;
        }
        if self.shape == BodyShape::Capsule {
            return true;
        }
        // Reached from inside the axis, the closest box point lies in the cross-section
        // disc there (the squared distance is smooth, so at an interior minimum the
        // offset is perpendicular to the axis): it is inside the cylinder.
        if t > 0.0 && t < 1.0 {
            return true;
        }
        // Reached at an end: a box that meets the cylinder meets its end disc there
        // (the segment from a shared point to the closest box point, which lies within r
        // of the end and not inside the cylinder's slab, crosses the disc), so the disc
        // decides.
        let Some((end, outward, len)) = self.flat_end(t) else {
            // A flat cylinder of no length: only its centre point is certain.
            return d2 <= 0.0;
        };
        // Rounding can put t on an end when f is flat there (a box face on the end
        // plane): the closest box point then lies inside the slab, within r of the end,
        // so inside the cylinder.
        let axial = -outward.dot(&(Vector3::from(q) - end));
        if axial >= 0.0 && axial <= len {
            return true;
        }
        // Most often the box lies wholly beyond the end plane, in the enclosing
        // capsule's cap (not wholly inside: its closest point is not).
        let height = outward.dot(&(Vector3::from(*center) - end));
        if height.abs() > box_spread(&outward, half) {
            return false;
        }
        disc_meets_box(&end, &outward, r, center, half)
    }
}

/// Half the extent of the box along the unit direction `u`.
#[inline]
pub(super) fn box_spread(u: &Vector3<f64>, half: &[f64; 3]) -> f64 {
    u.x.abs() * half[0] + u.y.abs() * half[1] + u.z.abs() * half[2]
}

/// The point of the box's section by the plane through `e` with unit normal `u`
/// nearest `e` (None when the plane misses the box). It solves min |x − e|² over the
/// box with u·(x − e) = 0, whose Lagrange dual is one-dimensional: for a multiplier λ
/// the minimiser over the box is the clamp of e − λu, and u·(x(λ) − e) falls with λ,
/// piecewise linearly between the λ where an axis starts or stops clamping. Those
/// breakpoints bracket its root (as in `segment_box_closest`), and no root means the
/// plane misses the box.
pub(super) fn plane_section_nearest(
    e: &Vector3<f64>,
    u: &Vector3<f64>,
    center: &[f64; 3],
    half: &[f64; 3],
) -> Option<Vector3<f64>> {
    let lo_corner = [
        center[0] - half[0],
        center[1] - half[1],
        center[2] - half[2],
    ];
    let hi_corner = [
        center[0] + half[0],
        center[1] + half[1],
        center[2] + half[2],
    ];
    // x(λ) − e per axis, and u·(x(λ) − e).
    let offset = |lambda: f64, i: usize| -> f64 {
        (e[i] - lambda * u[i]).clamp(lo_corner[i], hi_corner[i]) - e[i]
    };
    let gap = |lambda: f64| -> f64 {
        u[0] * offset(lambda, 0) + u[1] * offset(lambda, 1) + u[2] * offset(lambda, 2)
    };
    // (λ, gap) at the breakpoints, bracketing the root from both sides.
    let (mut lo, mut gap_lo) = (f64::NEG_INFINITY, f64::NAN);
    let (mut hi, mut gap_hi) = (f64::INFINITY, f64::NAN);
    for i in 0..3 {
        if u[i] == 0.0 {
            continue;
        }
        for bound in [lo_corner[i], hi_corner[i]] {
            let lambda = (e[i] - bound) / u[i];
            let g = gap(lambda);
            if g >= 0.0 && lambda > lo {
                (lo, gap_lo) = (lambda, g);
            }
            if g <= 0.0 && lambda < hi {
                (hi, gap_hi) = (lambda, g);
            }
        }
    }
    // Beyond the outermost breakpoints the gap is constant: without a breakpoint on
    // each side of zero the plane misses the box.
    if lo == f64::NEG_INFINITY || hi == f64::INFINITY {
        return None;
    }
    let lambda = if gap_lo == gap_hi {
        lo
    } else {
        lo + gap_lo * (hi - lo) / (gap_lo - gap_hi)
    };
    Some(Vector3::new(
        e[0] + offset(lambda, 0),
        e[1] + offset(lambda, 1),
        e[2] + offset(lambda, 2),
    ))
}

/// Does the disc (centre `e`, unit normal `u`, radius `r`) meet the box? When the
/// nearest point of the box's section by the disc's plane lies within r of `e`.
fn disc_meets_box(
    e: &Vector3<f64>,
    u: &Vector3<f64>,
    r: f64,
    center: &[f64; 3],
    half: &[f64; 3],
) -> bool {
    plane_section_nearest(e, u, center, half).is_some_and(|x| (x - e).norm_squared() <= r * r)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::synthetic::Rng;
    use parry3d_f64::na::Isometry3;
    use parry3d_f64::query;
    use parry3d_f64::shape::Cuboid;

    /// Brute-force cylinder–box overlap: sample the cylinder densely (surface and
    /// inside) and test the samples against the box grown by the sampling gap.
    #[test]
    fn cylinder_box_overlap_agrees_with_sampling() {
        let mut rng = Rng::new(12);
        let mut overlapping = 0;
        for _ in 0..400 {
            let mut v = || rng.uniform(-0.5, 0.5);
            let body = Body::cylinder([v(), v(), v()], [v(), v(), v()], v().abs() * 0.3 + 0.01);
            let center = [v() * 0.5, v() * 0.5, v() * 0.5];
            let half = [0.05, 0.05, 0.05];
            let exact = body.overlaps_box(&center, &half);
            let contact = body.box_contact(&center, &half);
            assert_eq!(exact, contact.distance <= 1e-9, "{contact:?}");
            // Dense samples of the cylinder.
            let c = &body.axis;
            let d = Vector3::from(c.b) - Vector3::from(c.a);
            let u = d
                .cross(&if d.x.abs() < 0.9 * d.norm() {
                    Vector3::x()
                } else {
                    Vector3::y()
                })
                .normalize();
            let w = d.normalize().cross(&u);
            let mut min_gap = f64::INFINITY;
            for i in 0..=40 {
                for j in 0..48 {
                    for k in 0..=6 {
                        let t = i as f64 / 40.0;
                        let ang = j as f64 / 48.0 * std::f64::consts::TAU;
                        let rad = c.radius * k as f64 / 6.0;
                        let p = Vector3::from(c.a) + d * t + (u * ang.cos() + w * ang.sin()) * rad;
                        let gap: f64 = (0..3)
                            .map(|a| ((p[a] - center[a]).abs() - half[a]).max(0.0).powi(2))
                            .sum::<f64>()
                            .sqrt();
                        min_gap = min_gap.min(gap);
                    }
                }
            }
            // The samples come within ~2 cm of every cylinder point here.
            if exact {
                assert!(
                    min_gap < 0.03,
                    "overlap claimed but samples are {min_gap} away"
                );
            } else {
                assert!(
                    min_gap > 0.0,
                    "a sample lies in the box but no overlap was reported"
                );
                assert!((contact.distance - min_gap).abs() < 0.03);
            }
            overlapping += usize::from(exact);
        }
        // Both answers are exercised.
        assert!(
            (40..=360).contains(&overlapping),
            "{overlapping} of 400 overlap"
        );
    }

    #[test]
    fn cylinder_box_test_equals_gjk() {
        let mut rng = Rng::new(21);
        let mut disagreements = 0;
        let mut hits = 0;
        for _ in 0..20_000 {
            let mut v = || rng.uniform(-0.3, 0.3);
            let (a, b) = ([v(), v(), v()], [v(), v(), v()]);
            let r = v().abs() * 0.3 + 0.005;
            let center = [v(), v(), v()];
            let half = [0.025 + v().abs() * 0.1, 0.025, 0.025 + v().abs() * 0.05];
            let body = Body::cylinder(a, b, r);
            let ours = body.overlaps_box(&center, &half);
            let cuboid = Cuboid::new(Vector3::from(half));
            let pose = Isometry3::translation(center[0], center[1], center[2]);
            let gap = query::distance(&body.parry_pose(), &body.cylinder_shape(), &pose, &cuboid)
                .unwrap();
            hits += usize::from(ours);
            // GJK's tolerance: only near-touching pairs may differ.
            if ours != (gap <= 0.0) {
                assert!(gap.abs() < 1e-6, "gap {gap} but ours says {ours}");
                disagreements += 1;
            }
        }
        assert!(hits > 500 && disagreements < 20, "{hits} {disagreements}");
    }

    #[test]
    fn disc_box_test_agrees_with_sampling() {
        let mut rng = Rng::new(31);
        let (mut hits, mut misses) = (0, 0);
        for _ in 0..3000 {
            let mut v = || rng.uniform(-0.2, 0.2);
            let e = Vector3::new(v(), v(), v());
            let u = Vector3::new(v(), v(), v()).normalize();
            let r = 0.02 + v().abs() * 0.3;
            let half = [0.025 + v().abs() * 0.1, 0.025, 0.025 + v().abs() * 0.05];
            // Boxes around the disc's rim and plane, where the answer is in doubt.
            let e1 = u.cross(&Vector3::x()).normalize();
            let e2 = u.cross(&e1);
            let c = e + e1 * (r * 5.0 * v()) + e2 * (r * 5.0 * v()) + u * (0.5 * v());
            let center = [c.x, c.y, c.z];
            let meets = disc_meets_box(&e, &u, r, &center, &half);
            // Dense polar samples of the disc: their nearest gap to the box.
            let mut min_gap = f64::INFINITY;
            for i in 0..=60 {
                for j in 0..96 {
                    let ang = j as f64 / 96.0 * std::f64::consts::TAU;
                    let p = e + (e1 * ang.cos() + e2 * ang.sin()) * (r * i as f64 / 60.0);
                    let gap: f64 = (0..3)
                        .map(|a| ((p[a] - center[a]).abs() - half[a]).max(0.0).powi(2))
                        .sum::<f64>()
                        .sqrt();
                    min_gap = min_gap.min(gap);
                }
            }
            // Samples are within r·π/96 of every disc point.
            let spacing = r * std::f64::consts::PI / 96.0 + r / 60.0;
            if meets {
                assert!(min_gap <= spacing, "meets, but samples are {min_gap} away");
                hits += 1;
            } else {
                assert!(min_gap > 0.0, "a disc sample lies in the box");
                misses += 1;
            }
        }
        assert!(hits > 300 && misses > 300, "{hits} {misses}");
    }

    #[test]
    fn box_faces_on_an_end_plane() {
        // Regressions from review: a box inside the slab whose face lies on the end plane
        // (the closest axis point then rounds onto the end) overlaps by millimetres.
        let body = Body::cylinder([0.42, 0.3, -0.5], [0.42, 0.3, 0.07500000000000001], 0.01);
        assert!(body.overlaps_box(&[0.4375, 0.3125, 0.0625], &[0.0125; 3]));
        let mut rng = Rng::new(61);
        let half = [0.02; 3];
        let mut overlapping = 0;
        for _ in 0..20_000 {
            // Axis along a grid direction, ending on a box face, offset across.
            let axis = rng.uniform(0.0, 3.0) as usize % 3;
            let (i, j) = ((axis + 1) % 3, (axis + 2) % 3);
            let mut a = [0.0; 3];
            let mut b = [0.0; 3];
            let face = 0.02 * (rng.uniform(-3.0, 3.0).round()) + 0.02;
            a[axis] = face - rng.uniform(0.05, 0.5);
            b[axis] = face;
            for k in [i, j] {
                let v = rng.uniform(-0.1, 0.1);
                a[k] = v;
                b[k] = v;
            }
            let body = Body::cylinder(a, b, rng.uniform(0.005, 0.08));
            let mut center = [0.0; 3];
            center[axis] = face - 0.02;
            for k in [i, j] {
                center[k] = 0.04 * (rng.uniform(-3.0, 3.0).round());
            }
            let cuboid = Cuboid::new(Vector3::from(half));
            let pose = Isometry3::translation(center[0], center[1], center[2]);
            let contact = query::contact(
                &body.parry_pose(),
                &body.cylinder_shape(),
                &pose,
                &cuboid,
                0.0,
            )
            .unwrap();
            let depth = contact.map_or(0.0, |c| -c.dist);
            if depth > 1e-9 {
                overlapping += 1;
                assert!(
                    body.overlaps_box(&center, &half),
                    "{body:?} {center:?} depth {depth}"
                );
            }
        }
        assert!(overlapping > 2000, "{overlapping}");
        // A cylinder of no length: its centre point.
        let flat = Body::cylinder([0.0; 3], [0.0; 3], 0.1);
        assert!(flat.overlaps_box(&[0.4, 0.0, 0.0], &[0.5; 3]));
        assert!(!flat.overlaps_box(&[2.0, 0.0, 0.0], &[0.5; 3]));
    }
}
