//! Capsules (a segment swept by a sphere) and the exact distance queries the robot
//! bodies need: point–segment, segment–box (axis-aligned voxel) and segment–segment.

use crate::geometry::{distance_squared, dot, sub};
use crate::robot::chain::Frame;

/// The segment `a`–`b` swept by a sphere of `radius` (in the frame it is given in).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Capsule {
    /// One end of the axis.
    pub a: [f64; 3],
    /// The other end of the axis.
    pub b: [f64; 3],
    /// Radius in metres.
    pub radius: f64,
}

impl Capsule {
    /// The capsule around the segment `a`–`b`.
    pub fn new(a: [f64; 3], b: [f64; 3], radius: f64) -> Self {
        Capsule { a, b, radius }
    }

    /// The capsule moved by `frame` (e.g. world_from_link).
    #[inline]
    pub fn placed(&self, frame: &Frame) -> Capsule {
        Capsule {
            a: frame.apply(&self.a),
            b: frame.apply(&self.b),
            radius: self.radius,
        }
    }

    /// Length of the axis segment, in metres.
    pub fn length(&self) -> f64 {
        distance_squared(&self.a, &self.b).sqrt()
    }

    /// Axis-aligned bounds (min, max).
    #[inline]
    pub fn aabb(&self) -> ([f64; 3], [f64; 3]) {
        let mut lo = [0.0; 3];
        let mut hi = [0.0; 3];
        for i in 0..3 {
            lo[i] = self.a[i].min(self.b[i]) - self.radius;
            hi[i] = self.a[i].max(self.b[i]) + self.radius;
        }
        (lo, hi)
    }

    /// Whether the point lies in the capsule (its surface included).
    #[inline]
    pub fn contains_point(&self, p: &[f64; 3]) -> bool {
        point_segment_distance_squared(&self.a, &self.b, p) <= self.radius * self.radius
    }

    /// Volume (m³), for choosing among fitted capsules.
    pub fn volume(&self) -> f64 {
        let r = self.radius;
        std::f64::consts::PI * r * r * (self.length() + 4.0 / 3.0 * r)
    }

    /// The point at parameter `t` ∈ [0, 1] along the axis.
    #[inline]
    pub fn axis_point(&self, t: f64) -> [f64; 3] {
        lerp(&self.a, &self.b, t)
    }
}

/// The point at parameter `t` on the segment `a`–`b` (0: `a`, 1: `b`).
#[inline]
pub fn lerp(a: &[f64; 3], b: &[f64; 3], t: f64) -> [f64; 3] {
    [
        a[0] + t * (b[0] - a[0]),
        a[1] + t * (b[1] - a[1]),
        a[2] + t * (b[2] - a[2]),
    ]
}

/// Parameter of the point of segment `a`–`b` closest to `p`.
#[inline]
pub fn closest_parameter_on_segment(a: &[f64; 3], b: &[f64; 3], p: &[f64; 3]) -> f64 {
    let d = sub(b, a);
    let len2 = dot(&d, &d);
    if len2 <= 0.0 {
        return 0.0;
    }
    (dot(&sub(p, a), &d) / len2).clamp(0.0, 1.0)
}

/// Squared distance from `p` to the segment `a`–`b`.
#[inline]
pub fn point_segment_distance_squared(a: &[f64; 3], b: &[f64; 3], p: &[f64; 3]) -> f64 {
    let t = closest_parameter_on_segment(a, b, p);
    distance_squared(&lerp(a, b, t), p)
}

/// Closest approach of a segment and an axis-aligned box (`center`, `half` sizes):
/// (squared distance, parameter on the segment, closest point on the box). Exact:
/// the squared distance f(t) is convex, smooth and piecewise quadratic, its pieces
/// changing where the segment crosses a face plane, so f' is continuous, increasing and
/// linear between those crossings. The crossings' slopes bracket the root (no sorting
/// needed), and on the bracket f' is one line whose root is read off its end values.
pub fn segment_box_closest(
    a: &[f64; 3],
    b: &[f64; 3],
    center: &[f64; 3],
    half: &[f64; 3],
) -> (f64, f64, [f64; 3]) {
    let p0 = sub(a, center);
    let d = sub(b, a);
    // f'(t) / 2.
    let slope = |t: f64| -> f64 {
        let mut s = 0.0;
        for i in 0..3 {
            let x = p0[i] + t * d[i];
            s += d[i] * (x - x.clamp(-half[i], half[i]));
        }
        s
    };
    let (s0, s1) = (slope(0.0), slope(1.0));
    let t = if s0 >= 0.0 {
        0.0
    } else if s1 <= 0.0 {
        1.0
    } else {
        let (mut lo, mut hi, mut s_lo, mut s_hi) = (0.0, 1.0, s0, s1);
        for i in 0..3 {
            if d[i] != 0.0 {
                let per = 1.0 / d[i];
                for bound in [-half[i], half[i]] {
                    let t = (bound - p0[i]) * per;
                    if t > lo && t < hi {
                        let s = slope(t);
                        if s < 0.0 {
                            (lo, s_lo) = (t, s);
                        } else {
                            (hi, s_hi) = (t, s);
                        }
                    }
                }
            }
        }
        (lo - s_lo * (hi - lo) / (s_hi - s_lo)).clamp(lo, hi)
    };
    let mut q = [0.0; 3];
    let mut dist2 = 0.0;
    for i in 0..3 {
        let x = p0[i] + t * d[i];
        let c = x.clamp(-half[i], half[i]);
        dist2 += (x - c) * (x - c);
        q[i] = c + center[i];
    }
    (dist2, t, q)
}

/// Closest points of segments `p1`–`q1` and `p2`–`q2`: (squared distance, s, t) with
/// the points at `p1 + s (q1 − p1)` and `p2 + t (q2 − p2)` (Ericson, Real-Time Collision
/// Detection §5.1.9).
pub fn segment_segment_closest(
    p1: &[f64; 3],
    q1: &[f64; 3],
    p2: &[f64; 3],
    q2: &[f64; 3],
) -> (f64, f64, f64) {
    let d1 = sub(q1, p1);
    let d2 = sub(q2, p2);
    let r = sub(p1, p2);
    let a = dot(&d1, &d1);
    let e = dot(&d2, &d2);
    let f = dot(&d2, &r);
    const EPS: f64 = 1e-18;
    let (s, t);
    if a <= EPS && e <= EPS {
        s = 0.0;
        t = 0.0;
    } else if a <= EPS {
        s = 0.0;
        t = (f / e).clamp(0.0, 1.0);
    } else {
        let c = dot(&d1, &r);
        if e <= EPS {
            t = 0.0;
            s = (-c / a).clamp(0.0, 1.0);
        } else {
            let b = dot(&d1, &d2);
            let denom = a * e - b * b;
            let mut s0 = if denom > 0.0 {
                ((b * f - c * e) / denom).clamp(0.0, 1.0)
            } else {
                0.0
            };
            let mut t0 = (b * s0 + f) / e;
            if t0 < 0.0 {
                t0 = 0.0;
                s0 = (-c / a).clamp(0.0, 1.0);
            } else if t0 > 1.0 {
                t0 = 1.0;
                s0 = ((b - c) / a).clamp(0.0, 1.0);
            }
            s = s0;
            t = t0;
        }
    }
    let c1 = lerp(p1, q1, s);
    let c2 = lerp(p2, q2, t);
    (distance_squared(&c1, &c2), s, t)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::synthetic::Rng;

    /// Brute force: the minimum over a dense sampling of the segment, refined by
    /// golden-section search on the convex distance.
    fn brute_segment_box(a: &[f64; 3], b: &[f64; 3], c: &[f64; 3], h: &[f64; 3]) -> f64 {
        let f = |t: f64| {
            let p = lerp(a, b, t);
            (0..3)
                .map(|i| {
                    let x = p[i] - c[i];
                    let e = (x.abs() - h[i]).max(0.0);
                    e * e
                })
                .sum::<f64>()
        };
        let (mut lo, mut hi) = (0.0, 1.0);
        let g = 0.5 * (5f64.sqrt() - 1.0);
        for _ in 0..200 {
            let m1 = hi - g * (hi - lo);
            let m2 = lo + g * (hi - lo);
            if f(m1) < f(m2) {
                hi = m2;
            } else {
                lo = m1;
            }
        }
        f(0.5 * (lo + hi)).min(f(0.0)).min(f(1.0))
    }

    #[test]
    fn segment_box_matches_brute_force() {
        let mut rng = Rng::new(7);
        for _ in 0..20_000 {
            let mut v = || rng.uniform(-1.0, 1.0);
            let a = [v(), v(), v()];
            let b = [v(), v(), v()];
            let c = [v() * 0.3, v() * 0.3, v() * 0.3];
            let h = [v().abs() * 0.2, v().abs() * 0.2, v().abs() * 0.2];
            let (d2, t, q) = segment_box_closest(&a, &b, &c, &h);
            let reference = brute_segment_box(&a, &b, &c, &h);
            assert!((d2 - reference).abs() < 1e-12, "{d2} vs {reference}");
            // The reported points realise the distance.
            let p = lerp(&a, &b, t);
            assert!((distance_squared(&p, &q) - d2).abs() < 1e-12);
            assert!((0..3).all(|i| (q[i] - c[i]).abs() <= h[i] + 1e-12));
        }
    }

    #[test]
    fn segment_segment_matches_sampling() {
        let mut rng = Rng::new(3);
        for _ in 0..2000 {
            let mut v = || rng.uniform(-1.0, 1.0);
            let (p1, q1, p2, q2) = (
                [v(), v(), v()],
                [v(), v(), v()],
                [v(), v(), v()],
                [v(), v(), v()],
            );
            let (d2, _, _) = segment_segment_closest(&p1, &q1, &p2, &q2);
            // The distance from a point moving along the first segment to the second
            // is convex in its parameter: a ternary search finds its minimum.
            let at = |s: f64| point_segment_distance_squared(&p2, &q2, &lerp(&p1, &q1, s)).sqrt();
            let (mut lo, mut hi) = (0.0f64, 1.0f64);
            for _ in 0..200 {
                let (a, b) = (lo + (hi - lo) / 3.0, hi - (hi - lo) / 3.0);
                if at(a) <= at(b) {
                    hi = b;
                } else {
                    lo = a;
                }
            }
            let best = at(0.0).min(at(1.0)).min(at((lo + hi) / 2.0));
            assert!((d2.sqrt() - best).abs() < 1e-9, "{} vs {best}", d2.sqrt());
        }
    }

    #[test]
    fn degenerate_segments() {
        let (d2, _, _) =
            segment_segment_closest(&[0.0; 3], &[0.0; 3], &[1.0, 0.0, 0.0], &[1.0, 0.0, 0.0]);
        assert_eq!(d2, 1.0);
        let (d2, _, q) =
            segment_box_closest(&[2.0, 0.0, 0.0], &[2.0, 0.0, 0.0], &[0.0; 3], &[0.5; 3]);
        assert_eq!((d2, q), (2.25, [0.5, 0.0, 0.0]));
    }
}
