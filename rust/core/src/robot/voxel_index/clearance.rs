//! How far is a body from the nearest occupied voxel box? Candidates from the
//! distance field's nearest-cell links, then exact contacts in order of their bound.

use super::{VoxelIndex, NONE};
use crate::error::Result;
use crate::robot::body::{Body, BodyBoxContact, NearestContact};
use crate::robot::capsule::point_segment_distance_squared;

const SQRT3: f64 = 1.732_050_807_568_877_2;

/// Result of a clearance query: distance from the capsule surface to the nearest
/// occupied voxel box (negative when they overlap), and the closest points.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Clearance {
    /// Metres from the body to the nearest occupied voxel box (negative: overlap).
    pub distance: f64,
    /// The body's point nearest the obstacle.
    pub on_body: [f64; 3],
    /// The obstacle's point nearest the body.
    pub on_obstacle: [f64; 3],
}

impl From<BodyBoxContact> for Clearance {
    fn from(contact: BodyBoxContact) -> Self {
        Clearance {
            distance: contact.distance,
            on_body: contact.on_body,
            on_obstacle: contact.on_box,
        }
    }
}

/// Reusable buffers of clearance queries.
#[derive(Default)]
pub struct ClearanceScratch {
    candidates: Vec<(f64, usize, u32)>,
    nearest: NearestContact<usize>,
}

impl VoxelIndex {
    /// Candidate nearest boxes of a body: the distance field's nearest-cell links at
    /// samples every half voxel along the axis, each with the enclosing capsule's
    /// distance to it (a lower bound on the body's), appended to `out` with `tag`.
    pub fn clearance_candidates(
        &self,
        body: &Body,
        tag: usize,
        out: &mut Vec<(f64, usize, u32)>,
    ) -> Result<()> {
        let res = self.resolution;
        let capsule = body.enclosing_capsule();
        let len = capsule.length();
        let steps = (2.0 * len / res).ceil().max(1.0) as usize;
        let half_diagonal = 0.5 * SQRT3 * res;
        let mut last = NONE;
        for s in 0..=steps {
            let p = capsule.axis_point(s as f64 / steps as f64);
            let Some((cell, _)) = self.cell_of(&p) else {
                return Err(self.outside_error(&p));
            };
            let near = self.field[cell].nearest;
            if near == NONE || near == last {
                continue;
            }
            last = near;
            // A cheap lower bound (the box's centre less its half diagonal) orders the
            // candidates; the exact distance is only computed for the few that lead.
            let centre = self.center_of(near as usize);
            let d = point_segment_distance_squared(&capsule.a, &capsule.b, &centre).sqrt();
            out.push((d - half_diagonal - capsule.radius, tag, near));
        }
        Ok(())
    }

    /// The closest of `bodies` to the candidates' boxes: candidates are taken in
    /// order of their lower bound until it passes the best found, closed-form contacts
    /// at once and cylinder-end ones at the end, only while they can still win (usually
    /// a few exact queries). Returns the index into `bodies` and the clearance; None
    /// when the index holds no occupied cell.
    pub fn bodies_clearance(
        &self,
        bodies: &[Body],
        scratch: &mut ClearanceScratch,
    ) -> Result<Option<(usize, Clearance)>> {
        // No early return for an empty index: the bodies are sampled all the same, so a
        // body outside the index is an error here as in the collision checks.
        let ClearanceScratch {
            candidates,
            nearest,
        } = scratch;
        candidates.clear();
        nearest.clear();
        for (tag, body) in bodies.iter().enumerate() {
            self.clearance_candidates(body, tag, candidates)?;
        }
        candidates.sort_unstable_by(|a, b| a.0.total_cmp(&b.0));
        let half = self.half();
        for &(bound, tag, cell) in candidates.iter() {
            if bound >= nearest.limit() {
                break;
            }
            nearest.offer(tag, &bodies[tag], &self.center_of(cell as usize), &half);
        }
        Ok(nearest.finish().map(|(tag, contact)| (tag, contact.into())))
    }

    /// Clearance of one body (see `bodies_clearance`).
    pub fn body_clearance(&self, body: &Body) -> Result<Option<Clearance>> {
        Ok(self
            .bodies_clearance(&[*body], &mut ClearanceScratch::default())?
            .map(|(_, c)| c))
    }

    /// How much `body_clearance` may exceed the true clearance: samples every
    /// res/2 (≤ res/4 from any axis point) and nearest-centre links (each cell centre
    /// within res·√3/2 of its points, box corners within res·√3/2 of their centres).
    pub fn clearance_error_bound(&self) -> f64 {
        self.resolution * (0.25 + 1.5 * SQRT3)
    }
}

#[cfg(test)]
mod tests {
    use super::super::tests::random_index;
    use super::*;
    use crate::robot::capsule::segment_box_closest;
    use crate::synthetic::Rng;

    #[test]
    fn clearance_is_close_to_brute_force() {
        let mut rng = Rng::new(4);
        let index = random_index(&mut rng, 0.05, 40);
        let half = index.half();
        let occupied = index.occupied_centers();
        for _ in 0..500 {
            let mut v = || rng.uniform(-0.4, 0.4);
            let c = Body::capsule([v(), v(), v()], [v(), v(), v()], 0.03);
            let got = index.body_clearance(&c).unwrap().unwrap();
            let brute = occupied
                .iter()
                .map(|o| segment_box_closest(&c.axis.a, &c.axis.b, o, &half).0.sqrt())
                .fold(f64::INFINITY, f64::min)
                - c.radius();
            assert!(got.distance >= brute - 1e-9, "{} < {brute}", got.distance);
            assert!(got.distance - brute <= index.clearance_error_bound());
        }
    }

    #[test]
    fn pruned_clearance_equals_every_box_tried() {
        // Mixed capsules and cylinders (whose flat ends take the deferred, iterative
        // path): the pruning must not change the nearest pair's distance.
        let mut rng = Rng::new(8);
        let index = random_index(&mut rng, 0.05, 60);
        let half = index.half();
        let occupied = index.occupied_centers();
        let mut scratch = ClearanceScratch::default();
        for i in 0..300 {
            let mut v = || rng.uniform(-0.4, 0.4);
            let bodies: Vec<Body> = (0..3)
                .map(|k| {
                    let (a, b) = ([v(), v(), v()], [v(), v(), v()]);
                    let r = 0.02 + 0.03 * v().abs();
                    if (i + k) % 2 == 0 {
                        Body::cylinder(a, b, r)
                    } else {
                        Body::capsule(a, b, r)
                    }
                })
                .collect();
            let (_, got) = index
                .bodies_clearance(&bodies, &mut scratch)
                .unwrap()
                .unwrap();
            // Every candidate box tried, no pruning.
            let mut candidates = Vec::new();
            for (k, b) in bodies.iter().enumerate() {
                index.clearance_candidates(b, k, &mut candidates).unwrap();
            }
            let unpruned = candidates
                .iter()
                .map(|&(_, k, cell)| {
                    bodies[k]
                        .box_contact(&index.center_of(cell as usize), &half)
                        .distance
                })
                .fold(f64::INFINITY, f64::min);
            assert_eq!(got.distance, unpruned, "case {i}");
            // And never above the distance to any occupied box by more than the bound.
            let brute = bodies
                .iter()
                .flat_map(|b| occupied.iter().map(|o| b.box_contact(o, &half).distance))
                .fold(f64::INFINITY, f64::min);
            assert!(
                got.distance >= brute - 1e-12
                    && got.distance <= brute + index.clearance_error_bound()
            );
        }
    }
}
