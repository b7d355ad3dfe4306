//! How far is a body from an axis-aligned box, and where are the closest points?
//! Closed form wherever it exists (every capsule, a cylinder reached from its side);
//! GJK for a cylinder reached near a flat end, which `NearestContact` puts off until
//! it can still matter.

use parry3d_f64::na::{Isometry3, Vector3};
use parry3d_f64::query;
use parry3d_f64::shape::Cuboid;

use super::box_overlap::{box_spread, plane_section_nearest};
use super::{Body, BodyShape};
use crate::robot::capsule::segment_box_closest;

/// Closest approach of a body and a box: signed distance (negative inside) and points.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct BodyBoxContact {
    /// Signed distance in metres: the gap, or minus the overlap depth.
    pub distance: f64,
    /// The body's point nearest the box.
    pub on_body: [f64; 3],
    /// The box's point nearest the body.
    pub on_box: [f64; 3],
}

/// See `Body::box_contact_step`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum ContactStep {
    /// The contact, from a closed form.
    Exact(BodyBoxContact),
    /// A cylinder reached near a flat end: the iterative query decides.
    Iterative {
        /// What the iterative query finds is at least this far (metres).
        lower_bound: f64,
        /// The enclosing capsule's contact (the answer if they touch).
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

    /// Offer the pair of `body` and the box at `center` (half sizes `half`), tagged
    /// `tag`: settled at once when in closed form, else kept while it may still win.
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
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::synthetic::Rng;

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
}
