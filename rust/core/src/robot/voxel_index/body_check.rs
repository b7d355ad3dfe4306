//! Does a body overlap an occupied voxel? The distance fields decide most axis
//! samples (free, or certainly colliding); exact body–box tests settle the rest.

use super::{VoxelIndex, NONE};
use crate::error::Result;
use crate::floor::fast_floor;
use crate::robot::body::{Body, BodyShape};

/// Axis samples per voxel length in collision tests: denser samples narrow the band
/// the distance field cannot decide (r + spacing/2), at the cost of more lookups.
const SAMPLES_PER_VOXEL: f64 = 1.0;

/// Outcome of the distance-field pass over a body's axis samples.
#[derive(Clone, Copy, Debug)]
pub enum SampleVerdict {
    /// A sample's ball reaches an occupied box: the body collides.
    Collides,
    /// Every sample is proven clear: the body is free.
    Free,
    /// Some samples are undecided; [`VoxelIndex::body_scan`] settles them.
    Undecided(UndecidedRuns),
}

/// Runs of consecutive axis samples the distance fields could not decide. Small (u16
/// sample numbers) because every body check returns one: at 150 bytes its copy was a
/// twentieth of a motion check.
#[derive(Clone, Copy, Debug)]
pub struct UndecidedRuns {
    steps: u32,
    runs: [(u16, u16); 8],
    len: u8,
    /// More runs than fit (or samples beyond u16): the scan covers the whole body.
    overflow: bool,
}

impl UndecidedRuns {
    fn push(&mut self, s: usize) {
        let Ok(s) = u16::try_from(s) else {
            self.overflow = true;
            return;
        };
        let len = self.len as usize;
        if len > 0 && self.runs[len - 1].1 as usize + 1 == s as usize {
            self.runs[len - 1].1 = s;
        } else if len < self.runs.len() {
            self.runs[len] = (s, s);
            self.len += 1;
        } else {
            self.overflow = true;
        }
    }
}

impl VoxelIndex {
    /// Does `body` overlap any occupied voxel box (touching counts)? Exact (see the
    /// module doc). Errors when the body leaves the indexed region.
    pub fn body_collides(&self, body: &Body) -> Result<bool> {
        Ok(match self.body_samples(body)? {
            SampleVerdict::Collides => true,
            SampleVerdict::Free => false,
            SampleVerdict::Undecided(runs) => self.body_scan(body, &runs),
        })
    }

    /// The distance-field pass alone: walk the axis samples, proving stretches free or
    /// the body colliding; what stays undecided is returned for `body_scan`.
    pub fn body_samples(&self, body: &Body) -> Result<SampleVerdict> {
        let capsule = body.enclosing_capsule();
        let r = capsule.radius;
        let len = capsule.length();
        // ceil(len / spacing) without a division or libm's ceil (neither is cheap next
        // to a sample's work).
        let wanted = SAMPLES_PER_VOXEL * len * self.inverse_resolution;
        let mut steps = wanted as usize;
        if (steps as f64) < wanted {
            steps = steps.saturating_add(1);
        }
        let steps = steps.max(1);
        let per_step = 1.0 / steps as f64;
        let spacing = len * per_step;
        let half = self.half();
        let mut runs = UndecidedRuns {
            steps: u32::try_from(steps).unwrap_or(u32::MAX),
            runs: [(0, 0); 8],
            len: 0,
            // (A body billions of samples long is scanned whole.)
            overflow: steps > u32::MAX as usize,
        };
        // The ball of radius `needed` around a sample covers the body's slice within half
        // a spacing of it: r + spacing/2 for a capsule (its rounded ends included), only
        // √(r² + (spacing/2)²) for a cylinder, whose flat ends stop at the end samples.
        // The cylinder's smaller band is what decides a UR upper arm beside the table.
        let needed = match body.shape {
            BodyShape::Capsule => r + 0.5 * spacing,
            // Not `hypot`: glibc's, careful about overflow, cost a twentieth of a check.
            BodyShape::Cylinder => (r * r + 0.25 * spacing * spacing).sqrt(),
        } + 1e-6;
        // A reciprocal once: divisions in the loop cost more than the rest of a step
        // (infinite for a point-like body, whose one sample then ends the walk).
        let per_spacing = 1.0 / spacing;
        // The walk may jump over the far end, so check it here: with both ends inside
        // the (convex) region, every sample is.
        if !self.contains(&capsule.b) {
            return Err(self.outside_error(&capsule.b));
        }
        let mut s = 0;
        while s <= steps {
            let t = (s as f64 * per_step).min(1.0);
            let p = capsule.axis_point(t);
            let Some((cell, centre)) = self.cell_of(&p) else {
                return Err(self.outside_error(&p));
            };
            let field = self.field[cell];
            if field.nearest == NONE {
                s += 1;
                continue;
            }
            // Every box is ≥ cell_distance from p (p is in the cell) and ≥ box_distance
            // − offset (the centre's bound moved by at most the offset).
            let mut clear = field.cell_distance as f64;
            if clear <= needed {
                let offset = crate::geometry::distance_squared(&p, &centre).sqrt();
                clear = clear.max(field.box_distance as f64 - offset);
            }
            if clear > needed {
                // Sphere tracing: a sample m spacings further on is ≥ clear − m·spacing
                // from every box, so it is free too while that exceeds `needed`.
                s = s
                    .saturating_add(((clear - needed) * per_spacing) as usize)
                    .saturating_add(1);
                continue;
            }
            // A ball inside the body that reaches the nearest box proves a collision; so
            // does that box overlapping the body (one exact test that usually spares
            // the scan of a colliding body).
            let near = self.center_of(field.nearest as usize);
            let inner = body.inner_radius_at(t);
            if point_box_distance_squared(&p, &near, &half) <= inner * inner
                || body.overlaps_box(&near, &half)
            {
                return Ok(SampleVerdict::Collides);
            }
            runs.push(s);
            s += 1;
        }
        Ok(if runs.len == 0 && !runs.overflow {
            SampleVerdict::Free
        } else {
            SampleVerdict::Undecided(runs)
        })
    }

    /// Exact tests for what `body_samples` left undecided: only boxes near undecided
    /// samples can touch the body, so scan the bounds of each run's stretch of the
    /// enclosing capsule.
    pub fn body_scan(&self, body: &Body, runs: &UndecidedRuns) -> bool {
        if runs.overflow {
            return self.body_collides_exact(body);
        }
        let capsule = body.enclosing_capsule();
        let steps = runs.steps as f64;
        runs.runs[..runs.len as usize].iter().any(|&(j0, j1)| {
            let t0 = ((j0 as f64 - 0.5) / steps).max(0.0);
            let t1 = ((j1 as f64 + 0.5) / steps).min(1.0);
            let piece = crate::robot::capsule::Capsule::new(
                capsule.axis_point(t0),
                capsule.axis_point(t1),
                capsule.radius,
            );
            self.for_each_occupied_near(&piece, |centre, half| body.overlaps_box(&centre, &half))
        })
    }

    /// Exact test against every occupied cell that can meet the body.
    pub fn body_collides_exact(&self, body: &Body) -> bool {
        self.for_each_occupied_near(body.enclosing_capsule(), |centre, half| {
            body.overlaps_box(&centre, &half)
        })
    }

    /// Calls `hit` with every run of occupied cells along x in `capsule`'s bounds, as
    /// one box (centre, half sizes), until it returns true (then true). A run's cells
    /// share faces, so their union is that box and one exact test stands for them all
    /// (a table top crossing the bounds is a handful of runs, not dozens of cells).
    fn for_each_occupied_near(
        &self,
        capsule: &crate::robot::capsule::Capsule,
        mut hit: impl FnMut([f64; 3], [f64; 3]) -> bool,
    ) -> bool {
        let (lo, hi) = capsule.aabb();
        let mut a = [0usize; 3];
        let mut b = [0usize; 3];
        for i in 0..3 {
            let l = (fast_floor(lo[i] / self.resolution) as i64 - self.origin[i]).max(0);
            let h = (fast_floor(hi[i] / self.resolution) as i64 - self.origin[i])
                .min(self.dims[i] as i64 - 1);
            if l > h {
                return false;
            }
            a[i] = l as usize;
            b[i] = h as usize;
        }
        let res = self.resolution;
        let coordinate =
            |axis: usize, c: usize| ((self.origin[axis] + c as i64) as f64 + 0.5) * res;
        for z in a[2]..=b[2] {
            let cz = coordinate(2, z);
            for y in a[1]..=b[1] {
                let cy = coordinate(1, y);
                let row = &self.occupied[self.linear([0, y, z])..];
                let mut x = a[0];
                while x <= b[0] {
                    if !row[x] {
                        x += 1;
                        continue;
                    }
                    let start = x;
                    while x < b[0] && row[x + 1] {
                        x += 1;
                    }
                    let cells = (x - start + 1) as f64;
                    let cx = 0.5 * (coordinate(0, start) + coordinate(0, x));
                    if hit([cx, cy, cz], [0.5 * res * cells, 0.5 * res, 0.5 * res]) {
                        return true;
                    }
                    x += 1;
                }
            }
        }
        false
    }
}

/// Squared distance from a point to an axis-aligned box.
#[inline]
pub(super) fn point_box_distance_squared(p: &[f64; 3], center: &[f64; 3], half: &[f64; 3]) -> f64 {
    (0..3)
        .map(|i| {
            let e = ((p[i] - center[i]).abs() - half[i]).max(0.0);
            e * e
        })
        .sum()
}

#[cfg(test)]
mod tests {
    use super::super::tests::random_index;
    use super::*;
    use crate::synthetic::Rng;

    /// A unit vector of uniformly random direction (rejection from the unit ball).
    fn random_unit(rng: &mut Rng) -> [f64; 3] {
        loop {
            let v = [0; 3].map(|_| rng.uniform(-1.0, 1.0));
            let n = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt();
            if n > 0.1 && n <= 1.0 {
                return v.map(|x| x / n);
            }
        }
    }

    #[test]
    fn body_tests_equal_exact_tests() {
        let mut rng = Rng::new(9);
        let mut hits = 0;
        for round in 0..20 {
            let index = random_index(&mut rng, 0.05, 5 + round * 10);
            let occupied = index.occupied_centers();
            let half = index.half();
            for i in 0..500 {
                let mut v = || rng.uniform(-0.4, 0.4);
                let (a, b) = ([v(), v(), v()], [v(), v(), v()]);
                let r = rng.uniform(0.0, 0.1);
                let body = if i % 2 == 0 {
                    Body::capsule(a, b, r)
                } else {
                    Body::cylinder(a, b, r)
                };
                let fast = index.body_collides(&body).unwrap();
                let brute = occupied.iter().any(|c| body.overlaps_box(c, &half));
                assert_eq!(fast, brute);
                assert_eq!(index.body_collides_exact(&body), brute);
                hits += usize::from(fast);
            }
        }
        assert!(hits > 1000 && hits < 9000, "{hits}");
    }

    /// Near misses decide the distance field's band: bodies of every orientation that
    /// touch a voxel are moved away in a random direction until they just stop touching
    /// the map (a table-like slab and scattered voxels), then left 0-3 cm further, so
    /// flat ends, rims and sides all pass close to boxes, between samples too.
    #[test]
    fn near_misses_equal_exact_tests() {
        let res = 0.05;
        let mut index = VoxelIndex::empty(res, [0.0; 3], 2.0).unwrap();
        index.mark_box([-5, -5, -1], [4, 4, -1]);
        let mut rng = Rng::new(12);
        for _ in 0..40 {
            index.mark_point([
                rng.uniform(-0.5, 0.5),
                rng.uniform(-0.5, 0.5),
                rng.uniform(0.0, 0.5),
            ]);
        }
        index.compute_distance_field();
        let occupied = index.occupied_centers();
        let half = index.half();
        let brute = |body: &Body| occupied.iter().any(|c| body.overlaps_box(c, &half));
        let (mut free, mut touching) = (0, 0);
        for i in 0..3000 {
            let c =
                occupied[(rng.uniform(0.0, 1.0) * occupied.len() as f64) as usize % occupied.len()];
            let (u, d) = (random_unit(&mut rng), random_unit(&mut rng));
            let (len, at, r) = (
                rng.uniform(0.02, 0.5),
                rng.uniform(0.0, 1.0),
                rng.uniform(0.01, 0.1),
            );
            let make = |s: f64| {
                let a = [0, 1, 2].map(|k| c[k] - u[k] * at * len + d[k] * s);
                let b = [0, 1, 2].map(|k| c[k] + u[k] * (1.0 - at) * len + d[k] * s);
                if i % 2 == 0 {
                    Body::capsule(a, b, r)
                } else {
                    Body::cylinder(a, b, r)
                }
            };
            // Bisect a distance at which the body stops touching the map.
            let (mut lo, mut hi) = (0.0, 1.2);
            if brute(&make(hi)) {
                continue;
            }
            for _ in 0..30 {
                let mid = 0.5 * (lo + hi);
                if brute(&make(mid)) {
                    lo = mid;
                } else {
                    hi = mid;
                }
            }
            for gap in [rng.uniform(0.0, 0.03), -rng.uniform(0.0, 0.003)] {
                let body = make(hi + gap);
                let expected = brute(&body);
                assert_eq!(index.body_collides(&body).unwrap(), expected, "{body:?}");
                if expected {
                    touching += 1;
                } else {
                    free += 1;
                }
            }
        }
        assert!(
            free > 2000 && touching > 2000,
            "{free} free, {touching} touching"
        );
    }

    /// The band's worst case: a cylinder's rim point midway between two axis samples
    /// (where the slice is farthest from its sample) pressed 0-4 mm into a voxel's
    /// corner, for random orientations, lengths, radii and sample counts. A band 10 %
    /// too small in its h term fails here (the random near misses above miss it).
    #[test]
    fn rim_between_samples_is_covered() {
        let res = 0.05;
        let mut index = VoxelIndex::empty(res, [0.0; 3], 1.0).unwrap();
        index.mark_point([0.5 * res; 3]);
        index.compute_distance_field();
        let (c, half) = (index.occupied_centers()[0], index.half());
        let mut rng = Rng::new(991);
        let mut touching = 0;
        for _ in 0..400_000 {
            // Axis u, and v across it towards the voxel.
            let (u, w) = (random_unit(&mut rng), random_unit(&mut rng));
            let along = u[0] * w[0] + u[1] * w[1] + u[2] * w[2];
            let v = [0, 1, 2].map(|k| w[k] - along * u[k]);
            let n = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt();
            if n < 1e-3 {
                continue;
            }
            let v = v.map(|x| x / n);
            let len = rng.uniform(0.3, 3.0) * res;
            let steps = (len / res).ceil().max(1.0);
            let h = len / steps;
            let r = rng.uniform(0.0, 1.5) * h;
            let axial = ((rng.uniform(0.0, steps)).floor().min(steps - 1.0) + 0.5) * h;
            let corner = [0, 1, 2].map(|k| c[k] - half[k] * v[k].signum());
            let depth = rng.uniform(0.0, 0.004);
            let a = [0, 1, 2].map(|k| corner[k] + depth * v[k] - axial * u[k] - r * v[k]);
            let b = [0, 1, 2].map(|k| a[k] + len * u[k]);
            let body = Body::cylinder(a, b, r);
            let exact = body.overlaps_box(&c, &half);
            touching += usize::from(exact);
            assert_eq!(index.body_collides(&body).unwrap(), exact, "{body:?}");
        }
        assert!(touching > 100_000, "{touching}");
    }

    /// Bodies longer than the index (here absurdly so) are an error, never a panic.
    #[test]
    fn a_huge_body_is_an_error() {
        let mut index = VoxelIndex::empty(0.05, [0.0; 3], 1.0).unwrap();
        index.mark_point([0.1, 0.1, 0.1]);
        index.compute_distance_field();
        let body = Body::capsule([0.0; 3], [1e18, 0.0, 0.0], 0.1);
        assert!(index.body_collides(&body).is_err());
    }

    /// A body of zero length (a ball) has one sample and an infinite sphere-tracing
    /// step; the walk must end, not wrap around.
    #[test]
    fn point_like_bodies_are_checked() {
        let mut index = VoxelIndex::empty(0.05, [0.0; 3], 1.0).unwrap();
        index.mark_point([0.325, 0.01, 0.01]);
        index.compute_distance_field();
        let (centre, half) = (index.occupied_centers()[0], index.half());
        for (x, hit) in [
            (0.0, false),
            (0.2, false),
            (0.25, false),
            (0.27, true),
            (0.32, true),
        ] {
            let ball = Body::capsule([x, 0.0, 0.0], [x, 0.0, 0.0], 0.04);
            assert_eq!(index.body_collides(&ball).unwrap(), hit, "{ball:?}");
            let disc = Body::cylinder([x, 0.0, 0.0], [x, 0.0, 0.0], 0.04);
            assert_eq!(
                index.body_collides(&disc).unwrap(),
                disc.overlaps_box(&centre, &half)
            );
        }
    }

    #[test]
    fn box_on_an_end_plane_through_the_index() {
        // Review regression: a cylinder whose end plane holds a box face, the box inside
        // its slab and radius (1 cm and 5.6 mm deep).
        let mut index = VoxelIndex::empty(0.02, [0.0; 3], 1.2).unwrap();
        index.mark_box([3, -2, 5], [3, -2, 5]);
        index.compute_distance_field();
        let body = Body::cylinder([0.07, 0.25, 0.14], [0.07, -0.04, 0.14], 0.03);
        assert!(index.body_collides_exact(&body));
        let body = Body::cylinder(
            [
                0.12574691552605238,
                0.25091236621507573,
                0.07503363052454111,
            ],
            [0.12574691552605238, -0.04, 0.07503363052454111],
            0.05776308886024466,
        );
        assert!(index.body_collides(&body).unwrap());
    }

    #[test]
    fn outside_the_region_is_an_error() {
        let index = VoxelIndex::empty(0.1, [0.0; 3], 1.0).unwrap();
        let c = Body::capsule([0.0; 3], [5.0, 0.0, 0.0], 0.1);
        assert!(index.body_collides(&c).is_err());
        // Ends just outside (the region has a spare cell: to 1.2), in free space the
        // walk would jump across.
        let mut index = VoxelIndex::empty(0.05, [0.0; 3], 1.1).unwrap();
        index.mark_point([-0.9, -0.9, -0.9]);
        index.compute_distance_field();
        for x in [1.21, 1.25, 1.3] {
            let c = Body::capsule([0.5, 0.0, 0.0], [x, 0.0, 0.0], 0.05);
            assert!(index.body_collides(&c).is_err(), "{x}");
        }
    }
}
