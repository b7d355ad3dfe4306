//! A link body: a capsule or a flat-ended cylinder around the segment `a`–`b`.
//!
//! Capsules have closed-form distances (segment geometry). Cylinders (Paper II's
//! choice, tighter for stubby links such as a UR shoulder) have closed-form overlap
//! tests with boxes; their distances to a box near a flat end, and cylinder pairs
//! that no closed-form test settles (touching axes' closest points, a separating
//! plane among four candidates), use parry's GJK queries.
//! Every cylinder lies inside the capsule with the same axis and radius, which the
//! fast conservative tests exploit.
//!
//! One concept per file: the body and its shape here, overlap with a box
//! (`box_overlap`), distance to a box (`box_contact`) and body pairs (`pair`).

mod box_contact;
mod box_overlap;
mod pair;

pub use box_contact::{BodyBoxContact, ContactStep, NearestContact};
pub use pair::AxisBounds;

use parry3d_f64::na::{Isometry3, Translation3, UnitQuaternion, Vector3};
use parry3d_f64::shape::Cylinder;

use crate::geometry::distance_squared;
use crate::robot::capsule::{lerp, Capsule};
use crate::robot::chain::Frame;

/// The shape of a [`Body`] around its axis.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum BodyShape {
    /// Round ends: every point within the radius of the axis segment.
    Capsule,
    /// Flat ends at the axis' end points.
    Cylinder,
}

/// A link body: a capsule or a flat-ended cylinder around the segment `axis.a`–`axis.b`
/// (metres, in whichever frame the body is given: link frame in a model, world frame
/// once placed).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Body {
    /// Axis and radius (for a cylinder: the axis between the flat end centres).
    pub axis: Capsule,
    /// Capsule or cylinder.
    pub shape: BodyShape,
}

impl Body {
    /// A capsule around the segment `a`–`b`.
    pub fn capsule(a: [f64; 3], b: [f64; 3], radius: f64) -> Self {
        Body {
            axis: Capsule::new(a, b, radius),
            shape: BodyShape::Capsule,
        }
    }

    /// A cylinder whose flat ends are centred on `a` and `b`.
    pub fn cylinder(a: [f64; 3], b: [f64; 3], radius: f64) -> Self {
        Body {
            axis: Capsule::new(a, b, radius),
            shape: BodyShape::Cylinder,
        }
    }

    /// Radius in metres.
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

    /// The body moved by `frame` (e.g. world_from_link).
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

    /// Volume in m³.
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

    /// Whether the point lies in the body (its surface included).
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
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn containment_by_shape() {
        let cyl = Body::cylinder([0.0; 3], [0.0, 0.0, 1.0], 0.1);
        let cap = Body::capsule([0.0; 3], [0.0, 0.0, 1.0], 0.1);
        let beyond_end = [0.0, 0.0, 1.05];
        assert!(!cyl.contains_point(&beyond_end) && cap.contains_point(&beyond_end));
        assert!(cyl.contains_point(&[0.09, 0.0, 0.5]));
        assert!((cyl.inner_radius_at(0.02) - 0.02).abs() < 1e-12);
    }
}
