//! Remove the robot from its own point clouds (Paper II): every point inside a padded
//! link body is dropped.

use crate::robot::model::PlacedBodies;
use crate::threads::map_parts;

/// `keep[i]` is false where point i lies inside (or on) any placed body.
pub fn self_filter(points: &[[f64; 3]], placed: &PlacedBodies) -> Vec<bool> {
    let (lo, hi) = placed.aabb();
    // Per-body bounds first: most points of a frame are nowhere near the robot.
    let boxes: Vec<([f64; 3], [f64; 3])> = placed.bodies.iter().map(|c| c.aabb()).collect();
    let keep_point =
        |p: &[f64; 3]| {
            let inside_all = (0..3).all(|i| p[i] >= lo[i] && p[i] <= hi[i]);
            if !inside_all {
                return true;
            }
            !placed.bodies.iter().zip(&boxes).any(|(c, (a, b))| {
                (0..3).all(|i| p[i] >= a[i] && p[i] <= b[i]) && c.contains_point(p)
            })
        };
    const CHUNK: usize = 16_384;
    let chunks: Vec<&[[f64; 3]]> = points.chunks(CHUNK).collect();
    map_parts(&chunks, |chunk| {
        chunk.iter().map(keep_point).collect::<Vec<bool>>()
    })
    .into_iter()
    .flatten()
    .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::robot::body::{Body, BodyShape};
    use crate::synthetic::Rng;

    #[test]
    fn equals_brute_force() {
        let mut rng = Rng::new(2);
        let placed = PlacedBodies {
            links: vec![1, 2],
            moving: vec![true, true],
            bodies: vec![
                Body::cylinder([0.0, 0.0, 0.0], [0.0, 0.0, 0.5], 0.08),
                Body::capsule([0.0, 0.0, 0.5], [0.4, 0.1, 0.6], 0.05),
            ],
        };
        let pts: Vec<[f64; 3]> = (0..50_000)
            .map(|_| {
                [
                    rng.uniform(-0.3, 0.6),
                    rng.uniform(-0.3, 0.3),
                    rng.uniform(-0.2, 0.8),
                ]
            })
            .collect();
        let keep = self_filter(&pts, &placed);
        for (p, k) in pts.iter().zip(&keep) {
            // Reference: distance to the axis segment, plus the end planes for cylinders.
            let inside = placed.bodies.iter().any(|b| {
                let c = &b.axis;
                let d = [c.b[0] - c.a[0], c.b[1] - c.a[1], c.b[2] - c.a[2]];
                let len2 = d.iter().map(|x| x * x).sum::<f64>();
                let t_raw = (0..3).map(|i| (p[i] - c.a[i]) * d[i]).sum::<f64>() / len2;
                let t = t_raw.clamp(0.0, 1.0);
                let dist2 = (0..3)
                    .map(|i| (p[i] - c.a[i] - t * d[i]).powi(2))
                    .sum::<f64>();
                match b.shape {
                    BodyShape::Capsule => dist2 <= c.radius * c.radius,
                    BodyShape::Cylinder => {
                        (0.0..=1.0).contains(&t_raw) && dist2 <= c.radius * c.radius
                    }
                }
            });
            assert_eq!(*k, !inside);
        }
        assert!(keep.iter().any(|k| !k) && keep.iter().any(|k| *k));
    }
}
