//! A link body: a capsule or a flat-ended cylinder around the segment `a`–`b`.
//!
//! Capsules have closed-form distances (segment geometry). Cylinders (Paper II's
//! choice, tighter for stubby links such as a UR shoulder) have closed-form overlap
//! tests with boxes; their distances to a box near a flat end, and cylinder pairs
//! that no closed-form test settles (touching axes' closest points, a separating
//! plane among four candidates), use parry's GJK queries.
//! Every cylinder lies inside the capsule with the same axis and radius, which the
//! fast conservative tests exploit.

use parry3d_f64::na::{Isometry3, Point3, Translation3, UnitQuaternion, Vector3};
use parry3d_f64::query;
use parry3d_f64::shape::{Capsule as ParryCapsule, Cuboid, Cylinder};

use crate::geometry::distance_squared;
use crate::robot::capsule::{
    lerp, point_segment_distance_squared, segment_box_closest, segment_segment_closest, Capsule,
};
use crate::robot::chain::Frame;

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum BodyShape {
    Capsule,
    Cylinder,
}

#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Body {
    /// Axis and radius (for a cylinder: the axis between the flat end centres).
    pub axis: Capsule,
    pub shape: BodyShape,
}

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

/// Closest approach of a body and a box: signed distance (negative inside) and points.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct BodyBoxContact {
    pub distance: f64,
    pub on_body: [f64; 3],
    pub on_box: [f64; 3],
}

/// See `Body::box_contact_step`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum ContactStep {
    Exact(BodyBoxContact),
    Iterative {
        lower_bound: f64,
        capsule: BodyBoxContact,
    },
}

/// A pair left for the iterative query: lower bound, tag, body, box centre and half
/// sizes, the enclosing capsule's contact.
type Waiting<T> = (f64, T, Body, [f64; 3], [f64; 3], BodyBoxContact);

/// The nearest of many body–box pairs, offered in any order: closed-form contacts
/// count at once; iterative ones wait, and in the end only those whose lower bound
/// can still beat the best are computed, most promising first.
pub struct NearestContact<T: Copy> {
    best: Option<(T, BodyBoxContact)>,
    waiting: Vec<Waiting<T>>,
}

impl<T: Copy> Default for NearestContact<T> {
    fn default() -> Self {
        NearestContact {
            best: None,
            waiting: Vec::new(),
        }
    }
}

impl<T: Copy> NearestContact<T> {
    /// Start over, keeping the allocation.
    pub fn clear(&mut self) {
        self.best = None;
        self.waiting.clear();
    }

    /// The best exact distance so far (∞ before any): pairs whose lower bound reaches
    /// it need not be offered.
    pub fn limit(&self) -> f64 {
        self.best.map_or(f64::INFINITY, |(_, c)| c.distance)
    }

    fn consider(&mut self, tag: T, contact: BodyBoxContact) {
        if contact.distance < self.limit() {
            self.best = Some((tag, contact));
        }
    }

    pub fn offer(&mut self, tag: T, body: &Body, center: &[f64; 3], half: &[f64; 3]) {
        match body.box_contact_step(center, half) {
            ContactStep::Exact(contact) => self.consider(tag, contact),
            ContactStep::Iterative {
                lower_bound,
                capsule,
            } => {
                if lower_bound < self.limit() {
                    self.waiting
                        .push((lower_bound, tag, *body, *center, *half, capsule));
                }
            }
        }
    }

    /// The nearest pair: its tag and contact (None if nothing was offered).
    pub fn finish(&mut self) -> Option<(T, BodyBoxContact)> {
        self.waiting.sort_unstable_by(|a, b| a.0.total_cmp(&b.0));
        for &(bound, tag, body, center, half, capsule) in &self.waiting {
            if bound >= self.limit() {
                break;
            }
            let contact = body.cylinder_end_contact(&center, &half, capsule);
            if contact.distance < self.limit() {
                self.best = Some((tag, contact));
            }
        }
        self.best
    }
}

impl Body {
    pub fn capsule(a: [f64; 3], b: [f64; 3], radius: f64) -> Self {
        Body {
            axis: Capsule::new(a, b, radius),
            shape: BodyShape::Capsule,
        }
    }

    pub fn cylinder(a: [f64; 3], b: [f64; 3], radius: f64) -> Self {
        Body {
            axis: Capsule::new(a, b, radius),
            shape: BodyShape::Cylinder,
        }
    }

    pub fn radius(&self) -> f64 {
        self.axis.radius
    }

    /// The body grown by `margin` in every direction (a cylinder also at its ends).
    pub fn grown(&self, margin: f64) -> Body {
        let mut out = *self;
        out.axis.radius += margin;
        if self.shape == BodyShape::Cylinder && margin != 0.0 {
            let c = &self.axis;
            let d = [c.b[0] - c.a[0], c.b[1] - c.a[1], c.b[2] - c.a[2]];
            let len = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
            if len > 0.0 {
                let k = margin / len;
                out.axis.a = [0, 1, 2].map(|i| c.a[i] - d[i] * k);
                out.axis.b = [0, 1, 2].map(|i| c.b[i] + d[i] * k);
            }
        }
        out
    }

    #[inline]
    pub fn placed(&self, frame: &Frame) -> Body {
        Body {
            axis: self.axis.placed(frame),
            shape: self.shape,
        }
    }

    /// The capsule with the same axis and radius (equal to a capsule body, a superset
    /// of a cylinder body).
    #[inline]
    pub fn enclosing_capsule(&self) -> &Capsule {
        &self.axis
    }

    pub fn volume(&self) -> f64 {
        match self.shape {
            BodyShape::Capsule => self.axis.volume(),
            BodyShape::Cylinder => {
                let r = self.axis.radius;
                std::f64::consts::PI * r * r * self.axis.length()
            }
        }
    }

    /// Bounds (min, max): the enclosing capsule's, which hold the body.
    #[inline]
    pub fn aabb(&self) -> ([f64; 3], [f64; 3]) {
        self.axis.aabb()
    }

    #[inline]
    pub fn contains_point(&self, p: &[f64; 3]) -> bool {
        let c = &self.axis;
        match self.shape {
            BodyShape::Capsule => c.contains_point(p),
            BodyShape::Cylinder => {
                let d = [c.b[0] - c.a[0], c.b[1] - c.a[1], c.b[2] - c.a[2]];
                let len2 = d[0] * d[0] + d[1] * d[1] + d[2] * d[2];
                let along =
                    (p[0] - c.a[0]) * d[0] + (p[1] - c.a[1]) * d[1] + (p[2] - c.a[2]) * d[2];
                if along < 0.0 || along > len2 {
                    return false;
                }
                let t = if len2 > 0.0 { along / len2 } else { 0.0 };
                distance_squared(&lerp(&c.a, &c.b, t), p) <= c.radius * c.radius
            }
        }
    }

    /// Radius of the largest ball centred at axis parameter `t` that lies in the body.
    #[inline]
    pub fn inner_radius_at(&self, t: f64) -> f64 {
        match self.shape {
            BodyShape::Capsule => self.axis.radius,
            BodyShape::Cylinder => {
                let len = self.axis.length();
                self.axis.radius.min(t * len).min((1.0 - t) * len).max(0.0)
            }
        }
    }

    /// The body as a parry shape and its pose (cylinders are along Y in parry).
    fn parry_pose(&self) -> Isometry3<f64> {
        let a = Vector3::from(self.axis.a);
        let b = Vector3::from(self.axis.b);
        let d = b - a;
        let rotation = if d.norm() > 0.0 {
            UnitQuaternion::rotation_between(&Vector3::y(), &d).unwrap_or_else(|| {
                UnitQuaternion::from_axis_angle(&Vector3::x_axis(), std::f64::consts::PI)
            })
        } else {
            UnitQuaternion::identity()
        };
        Isometry3::from_parts(Translation3::from((a + b) * 0.5), rotation)
    }

    fn cylinder_shape(&self) -> Cylinder {
        Cylinder::new(0.5 * self.axis.length(), self.axis.radius.max(0.0))
    }

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

    /// Distance to the box and the closest points; negative when they overlap (then
    /// the depth is the enclosing capsule's, an over-estimate for cylinders).
    pub fn box_contact(&self, center: &[f64; 3], half: &[f64; 3]) -> BodyBoxContact {
        match self.box_contact_step(center, half) {
            ContactStep::Exact(contact) => contact,
            ContactStep::Iterative { capsule, .. } => {
                self.cylinder_end_contact(center, half, capsule)
            }
        }
    }

    /// `box_contact` as far as closed forms go: every capsule, and a cylinder reached
    /// from inside its axis or overlapping the box, is exact; a cylinder reached at a
    /// flat end needs `cylinder_end_contact` (iterative), and comes with a cheap lower
    /// bound on what that finds.
    pub fn box_contact_step(&self, center: &[f64; 3], half: &[f64; 3]) -> ContactStep {
        let (d2, t, q) = segment_box_closest(&self.axis.a, &self.axis.b, center, half);
        let on_axis = self.axis.axis_point(t);
        let d = d2.sqrt();
        let on_body = if d > 0.0 {
            let k = self.axis.radius / d;
            [0, 1, 2].map(|i| on_axis[i] + (q[i] - on_axis[i]) * k)
        } else {
            on_axis
        };
        let capsule = BodyBoxContact {
            distance: d - self.axis.radius,
            on_body,
            on_box: q,
        };
        // The capsule's closest point lies on the side a cylinder shares when it is
        // reached from inside the axis (the offset is then perpendicular to the axis).
        let interior = t > 0.0 && t < 1.0;
        if self.shape == BodyShape::Capsule || (interior && capsule.distance > 0.0) {
            return ContactStep::Exact(capsule);
        }
        if capsule.distance <= 0.0 && self.overlaps_box(center, half) {
            return ContactStep::Exact(capsule);
        }
        if let Some(contact) = self.end_face_contact(t, center, half) {
            return ContactStep::Exact(contact);
        }
        // The enclosing capsule's distance is a lower bound; so is the box's gap to
        // the end plane it is reached at.
        ContactStep::Iterative {
            lower_bound: capsule.distance.max(self.end_plane_gap(t, center, half)),
            capsule,
        }
    }

    /// A cylinder's closest points to a box near its flat end (GJK, no penetration);
    /// `capsule` is the enclosing capsule's contact, the answer when they touch.
    pub fn cylinder_end_contact(
        &self,
        center: &[f64; 3],
        half: &[f64; 3],
        capsule: BodyBoxContact,
    ) -> BodyBoxContact {
        let cuboid = Cuboid::new(Vector3::from(*half));
        let box_pose = Isometry3::translation(center[0], center[1], center[2]);
        match query::closest_points(
            &self.parry_pose(),
            &self.cylinder_shape(),
            &box_pose,
            &cuboid,
            f64::MAX,
        ) {
            Ok(query::ClosestPoints::WithinMargin(p1, p2)) => BodyBoxContact {
                distance: (p2 - p1).norm(),
                on_body: [p1.x, p1.y, p1.z],
                on_box: [p2.x, p2.y, p2.z],
            },
            // Touching (or unsupported): the capsule's answer never overstates the gap.
            _ => capsule,
        }
    }

    /// A cylinder's contact with a box wholly beyond its end `t` (0: a, 1: b) when the
    /// box's side facing the end face comes within the cylinder's radius of the axis:
    /// no box point is nearer the end plane, and one is straight across from the face,
    /// so the gap to the plane is the distance. None otherwise.
    fn end_face_contact(
        &self,
        t: f64,
        center: &[f64; 3],
        half: &[f64; 3],
    ) -> Option<BodyBoxContact> {
        let gap = self.end_plane_gap(t, center, half);
        let (end, outward, _) = self.flat_end(t)?;
        if gap.is_nan() || gap <= 0.0 {
            return None;
        }
        // The box's side facing the end: its section by the plane at the gap.
        let on_box = plane_section_nearest(&(end + outward * gap), &outward, center, half)?;
        let w = on_box - end;
        let across = w - outward * outward.dot(&w);
        if across.norm_squared() > self.axis.radius * self.axis.radius {
            return None;
        }
        let on_body = end + across;
        Some(BodyBoxContact {
            distance: (on_box - on_body).norm(),
            on_body: [on_body.x, on_body.y, on_body.z],
            on_box: [on_box.x, on_box.y, on_box.z],
        })
    }

    /// How far the box lies beyond the cylinder's end plane at `t` (0: end a, 1: end b),
    /// 0 when it reaches the slab between the planes.
    fn end_plane_gap(&self, t: f64, center: &[f64; 3], half: &[f64; 3]) -> f64 {
        let Some((end, outward, _)) = self.flat_end(t) else {
            return 0.0;
        };
        let height = outward.dot(&(Vector3::from(*center) - end));
        (height - box_spread(&outward, half)).max(0.0)
    }

    /// The end at `t` (0: a, 1: b) of a cylinder of some length: its centre, the unit
    /// normal pointing out of the cylinder there, and the length.
    fn flat_end(&self, t: f64) -> Option<(Vector3<f64>, Vector3<f64>, f64)> {
        let c = &self.axis;
        let d = Vector3::new(c.b[0] - c.a[0], c.b[1] - c.a[1], c.b[2] - c.a[2]);
        let len = d.norm();
        if len == 0.0 {
            return None;
        }
        Some(if t <= 0.0 {
            (Vector3::from(c.a), -d / len, len)
        } else {
            (Vector3::from(c.b), d / len, len)
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

/// Half the extent of the box along the unit direction `u`.
#[inline]
fn box_spread(u: &Vector3<f64>, half: &[f64; 3]) -> f64 {
    u.x.abs() * half[0] + u.y.abs() * half[1] + u.z.abs() * half[2]
}

/// The point of the box's section by the plane through `e` with unit normal `u`
/// nearest `e` (None when the plane misses the box). It solves min |x − e|² over the
/// box with u·(x − e) = 0, whose Lagrange dual is one-dimensional: for a multiplier λ
/// the minimiser over the box is the clamp of e − λu, and u·(x(λ) − e) falls with λ,
/// piecewise linearly between the λ where an axis starts or stops clamping. Those
/// breakpoints bracket its root (as in `segment_box_closest`), and no root means the
/// plane misses the box.
fn plane_section_nearest(
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
    fn cylinder_box_distance_equals_gjk() {
        // Boxes all around cylinders, many beyond a flat end (the closed-form end-face
        // case) and near the rim (GJK).
        let mut rng = Rng::new(44);
        let mut end_face = 0;
        for _ in 0..5000 {
            let mut v = || rng.uniform(-0.3, 0.3);
            let (a, b) = ([v(), v(), v()], [v(), v(), v()]);
            let body = Body::cylinder(a, b, 0.02 + v().abs() * 0.2);
            let axis = Vector3::from(b) - Vector3::from(a);
            let c = Vector3::from(b)
                + axis.normalize() * (0.3 * v().abs())
                + Vector3::new(v(), v(), v()) * 0.5;
            let (center, half) = ([c.x, c.y, c.z], [0.025, 0.025 + v().abs() * 0.05, 0.025]);
            let contact = body.box_contact(&center, &half);
            let cuboid = Cuboid::new(Vector3::from(half));
            let pose = Isometry3::translation(center[0], center[1], center[2]);
            let gap = query::distance(&body.parry_pose(), &body.cylinder_shape(), &pose, &cuboid)
                .unwrap();
            if gap > 1e-6 {
                assert!(
                    (contact.distance - gap).abs() < 1e-6,
                    "{} vs {gap}",
                    contact.distance
                );
                let pair = Vector3::from(contact.on_box) - Vector3::from(contact.on_body);
                assert!((pair.norm() - contact.distance).abs() < 1e-9);
                assert!((0..3).all(|i| (contact.on_box[i] - center[i]).abs() <= half[i] + 1e-12));
                end_face += usize::from(body.end_face_contact(1.0, &center, &half).is_some());
            }
        }
        assert!(end_face > 100, "{end_face}");
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
    fn containment_by_shape() {
        let cyl = Body::cylinder([0.0; 3], [0.0, 0.0, 1.0], 0.1);
        let cap = Body::capsule([0.0; 3], [0.0, 0.0, 1.0], 0.1);
        let beyond_end = [0.0, 0.0, 1.05];
        assert!(!cyl.contains_point(&beyond_end) && cap.contains_point(&beyond_end));
        assert!(cyl.contains_point(&[0.09, 0.0, 0.5]));
        assert!((cyl.inner_radius_at(0.02) - 0.02).abs() < 1e-12);
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
