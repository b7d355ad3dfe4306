//! Do two bodies touch? Axis-aligned bounds first, then the axes' closest approach,
//! a few candidate separating planes, and GJK for what those leave open.

use parry3d_f64::na::{Isometry3, Point3, Vector3};
use parry3d_f64::query;
use parry3d_f64::shape::Capsule as ParryCapsule;

use super::{Body, BodyShape};
use crate::robot::capsule::{lerp, segment_segment_closest};

/// Axis-aligned bounds kept as twice the centre and twice the half extent per axis:
/// the disjointness test is then three subtractions and compares, with none of the
/// min/max that bounds as corners need (which cost more than the test they save).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct AxisBounds {
    twice_centre: [f64; 3],
    /// Grown by a slack far above rounding (1e-9 relative, of the extent and the
    /// centre's magnitude): only a filter in front of the exact tests, it must let bodies
    /// that exactly touch (which counts as touching) reach them.
    twice_extent: [f64; 3],
}

impl AxisBounds {
    /// Certainly apart on some axis.
    #[inline]
    pub fn disjoint(&self, other: &AxisBounds) -> bool {
        (0..3).any(|i| {
            (self.twice_centre[i] - other.twice_centre[i]).abs()
                > self.twice_extent[i] + other.twice_extent[i]
        })
    }
}

impl Body {
    /// Half the extent of the body along the unit direction `w` (its projection is
    /// centre·w ± this): the axis' share plus the rim's (a cylinder's flat ends) or
    /// the full radius (a capsule's round ends).
    #[inline]
    fn spread_along(&self, w: &Vector3<f64>) -> f64 {
        let d = Vector3::from(self.axis.b) - Vector3::from(self.axis.a);
        let along = d.dot(w).abs();
        let r = self.axis.radius;
        match self.shape {
            BodyShape::Capsule => 0.5 * along + r,
            BodyShape::Cylinder => {
                let len2 = d.norm_squared();
                let cos2 = if len2 > 0.0 {
                    along * along / len2
                } else {
                    1.0
                };
                0.5 * along + r * (1.0 - cos2).max(0.0).sqrt()
            }
        }
    }

    /// Is there a separating plane among a few candidates: normal to either axis, to
    /// both, or along `closest` (between the axes' closest points)? True proves the
    /// bodies apart; false proves nothing.
    fn separated_from(&self, other: &Body, closest: &Vector3<f64>) -> bool {
        let centre = |b: &Body| 0.5 * (Vector3::from(b.axis.a) + Vector3::from(b.axis.b));
        let gap = centre(other) - centre(self);
        let d1 = Vector3::from(self.axis.b) - Vector3::from(self.axis.a);
        let d2 = Vector3::from(other.axis.b) - Vector3::from(other.axis.a);
        [*closest, d1, d2, d1.cross(&d2)].iter().any(|w| {
            let n = w.norm();
            if n < 1e-12 {
                return false;
            }
            let w = w / n;
            // A strict margin: touching counts as meeting, so only a clear gap separates.
            gap.dot(&w).abs() > self.spread_along(&w) + other.spread_along(&w) + 1e-12
        })
    }

    /// Do two bodies touch?
    #[inline]
    pub fn intersects(&self, other: &Body) -> bool {
        !self.bounds().disjoint(&other.bounds()) && self.intersects_within_bounds(other)
    }

    /// The enclosing capsule's axis-aligned bounds, in the form `AxisBounds::disjoint`
    /// tests fastest.
    #[inline]
    pub fn bounds(&self) -> AxisBounds {
        let c = &self.axis;
        let twice_centre = [0, 1, 2].map(|i| c.a[i] + c.b[i]);
        AxisBounds {
            twice_centre,
            // The slack (see `AxisBounds::disjoint`) is part of the extent, so a pair's
            // test stays three compares.
            twice_extent: [0, 1, 2].map(|i| {
                let extent = (c.a[i] - c.b[i]).abs() + 2.0 * c.radius;
                extent + 1e-9 * (extent + twice_centre[i].abs())
            }),
        }
    }

    /// `intersects` for bodies whose bounds overlap (the exact part; most pairs of a
    /// robot's links are far apart and never get here).
    #[inline(never)]
    pub fn intersects_within_bounds(&self, other: &Body) -> bool {
        let (p, q) = (&self.axis, &other.axis);
        if self.shape == BodyShape::Capsule && other.shape == BodyShape::Capsule {
            let (d2, _, _) = segment_segment_closest(&p.a, &p.b, &q.a, &q.b);
            let r = p.radius + q.radius;
            return d2 <= r * r;
        }
        // Quick reject with the enclosing capsules.
        let (d2, s, t) = segment_segment_closest(&p.a, &p.b, &q.a, &q.b);
        let r = p.radius + q.radius;
        if d2 > r * r {
            return false;
        }
        // Closest where each cylinder's axis is interior: the connecting segment is then
        // perpendicular to both axes, and its point r₁ from the first axis lies in both
        // bodies (a capsule holds the ball around any of its axis points).
        let inside =
            |shape: BodyShape, at: f64| shape == BodyShape::Capsule || (at > 0.0 && at < 1.0);
        if inside(self.shape, s) && inside(other.shape, t) {
            return true;
        }
        // Near misses at a flat end are most of what reaches here (a robot's
        // neighbouring links): a separating plane found in closed form spares GJK.
        let closest = Vector3::from(lerp(&q.a, &q.b, t)) - Vector3::from(lerp(&p.a, &p.b, s));
        if self.separated_from(other, &closest) {
            return false;
        }
        let shape = |b: &Body| -> Box<dyn parry3d_f64::shape::Shape> {
            match b.shape {
                BodyShape::Capsule => Box::new(ParryCapsule::new(
                    Point3::from(b.axis.a),
                    Point3::from(b.axis.b),
                    b.axis.radius.max(0.0),
                )),
                BodyShape::Cylinder => Box::new(b.cylinder_shape()),
            }
        };
        let pose = |b: &Body| match b.shape {
            BodyShape::Capsule => Isometry3::identity(),
            BodyShape::Cylinder => b.parry_pose(),
        };
        query::intersection_test(
            &pose(self),
            shape(self).as_ref(),
            &pose(other),
            shape(other).as_ref(),
        )
        .unwrap_or(true)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::synthetic::Rng;

    #[test]
    fn body_pairs_agree_with_gjk() {
        let mut rng = Rng::new(52);
        let (mut hits, mut shortcut) = (0, 0);
        for i in 0..20_000 {
            let mut v = || rng.uniform(-0.3, 0.3);
            let mut body = |k: usize| {
                let (a, b, r) = ([v(), v(), v()], [v(), v(), v()], 0.02 + v().abs() * 0.3);
                if (i + k).is_multiple_of(3) {
                    Body::capsule(a, b, r)
                } else {
                    Body::cylinder(a, b, r)
                }
            };
            let (x, y) = (body(0), body(1));
            let parry = |b: &Body| -> (Isometry3<f64>, Box<dyn parry3d_f64::shape::Shape>) {
                match b.shape {
                    BodyShape::Capsule => (
                        Isometry3::identity(),
                        Box::new(ParryCapsule::new(
                            Point3::from(b.axis.a),
                            Point3::from(b.axis.b),
                            b.axis.radius,
                        )),
                    ),
                    BodyShape::Cylinder => (b.parry_pose(), Box::new(b.cylinder_shape())),
                }
            };
            let ((px, sx), (py, sy)) = (parry(&x), parry(&y));
            let gap = query::distance(&px, sx.as_ref(), &py, sy.as_ref()).unwrap();
            let ours = x.intersects(&y);
            // GJK's tolerance: only near-touching pairs may differ.
            if ours != (gap <= 0.0) {
                assert!(gap.abs() < 1e-6, "gap {gap} but ours says {ours}");
            }
            hits += usize::from(ours);
            let (_, s, t) = segment_segment_closest(&x.axis.a, &x.axis.b, &y.axis.a, &y.axis.b);
            shortcut += usize::from(ours && s > 0.0 && s < 1.0 && t > 0.0 && t < 1.0);
        }
        assert!(hits > 2000 && shortcut > 1000, "{hits} {shortcut}");
    }

    #[test]
    fn separating_planes_are_sound_and_catch_most_near_misses() {
        // Pairs whose enclosing capsules meet (what the plane test is asked about):
        // it must never separate bodies GJK finds touching, and it should settle
        // most of the ones GJK finds apart (else GJK runs for every near miss).
        let mut rng = Rng::new(7);
        let (mut apart, mut settled, mut touching) = (0, 0, 0);
        while apart < 3000 || touching < 3000 {
            let mut v = || rng.uniform(-0.2, 0.2);
            let mut cylinder =
                || Body::cylinder([v(), v(), v()], [v(), v(), v()], 0.03 + 0.1 * v().abs());
            let (x, y) = (cylinder(), cylinder());
            let (d2, s, t) = segment_segment_closest(&x.axis.a, &x.axis.b, &y.axis.a, &y.axis.b);
            let r = x.radius() + y.radius();
            if d2 > r * r {
                continue;
            }
            let gap = query::distance(
                &x.parry_pose(),
                &x.cylinder_shape(),
                &y.parry_pose(),
                &y.cylinder_shape(),
            )
            .unwrap();
            let closest = Vector3::from(lerp(&y.axis.a, &y.axis.b, t))
                - Vector3::from(lerp(&x.axis.a, &x.axis.b, s));
            let separated = x.separated_from(&y, &closest);
            if gap <= 1e-9 {
                assert!(!separated, "a plane separates touching bodies (gap {gap})");
                touching += 1;
            } else {
                apart += 1;
                settled += usize::from(separated);
            }
        }
        assert!(
            settled * 2 > apart,
            "planes settled only {settled} of {apart} near misses"
        );
    }

    #[test]
    fn body_pairs() {
        let a = Body::cylinder([0.0; 3], [0.0, 0.0, 1.0], 0.1);
        let b = Body::capsule([0.25, 0.0, 0.5], [1.0, 0.0, 0.5], 0.1);
        assert!(!a.intersects(&b));
        let c = Body::capsule([0.15, 0.0, 0.5], [1.0, 0.0, 0.5], 0.1);
        assert!(a.intersects(&c));
        // Beyond the cylinder's flat end but inside its enclosing capsule.
        let d = Body::capsule([0.0, 0.0, 1.15], [0.0, 0.0, 2.0], 0.1);
        assert!(!a.intersects(&d));
    }

    /// The bounds filter must not decide pairs that exactly touch (touching counts):
    /// capsules stacked along z with their ends one radius sum apart, at random places
    /// and sizes, where rounding puts the gap on either side of the bounds' reach.
    #[test]
    fn bounds_never_reject_touching_pairs() {
        let mut rng = crate::synthetic::Rng::new(21);
        let mut touching = 0;
        for _ in 0..20_000 {
            let (x, y) = (rng.uniform(-1.0, 1.0), rng.uniform(-1.0, 1.0));
            let (z, len) = (rng.uniform(-1.0, 1.0), rng.uniform(0.0, 0.5));
            let (r1, r2) = (rng.uniform(0.0, 0.2), rng.uniform(0.0, 0.2));
            let p = Body::capsule([x, y, z], [x, y, z + len], r1);
            let z2 = z + len + r1 + r2;
            let q = Body::capsule([x, y, z2], [x + rng.uniform(-0.1, 0.1), y, z2], r2);
            let exact = p.intersects_within_bounds(&q);
            touching += usize::from(exact);
            assert_eq!(p.intersects(&q), exact, "{p:?} {q:?}");
        }
        assert!(touching > 1000, "{touching}");
    }
}
