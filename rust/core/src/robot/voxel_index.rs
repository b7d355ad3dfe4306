//! A dense index of a map's occupied voxels around the robot, with a Euclidean
//! distance transform (distance from every cell centre to the nearest occupied cell
//! centre, and which cell that is), for fast conservative capsule tests and clearance.
//!
//! Capsule tests walk sample points along the capsule's axis: a sample whose cell is
//! far enough from every occupied cell proves its part of the capsule free, a sample
//! whose nearest occupied box lies within the radius proves a collision, and anything
//! in between falls back to exact segment–box tests over the capsule's cells. So the
//! answer is exact; the distance field only makes it fast.

use crate::error::{Error, Result};
use crate::floor::fast_floor;
use crate::octree::{OcTree, OcTreeKey, TREE_DEPTH};
use crate::robot::body::{Body, BodyBoxContact, BodyShape, NearestContact};
use crate::robot::capsule::point_segment_distance_squared;

const NONE: u32 = u32::MAX;
/// Axis samples per voxel length in collision tests: denser samples narrow the band
/// the distance field cannot decide (r + spacing/2), at the cost of more lookups.
const SAMPLES_PER_VOXEL: f64 = 1.0;
const SQRT3: f64 = 1.732_050_807_568_877_2;

/// Which voxels of the map count as obstacles.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum VoxelSource {
    /// Every occupied leaf of the occupancy map.
    Occupied,
    /// Only the cells hit in the last closed danger frame (what the cameras see now).
    CurrentObstacles,
}

/// Result of a clearance query: distance from the capsule surface to the nearest
/// occupied voxel box (negative when they overlap), and the closest points.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Clearance {
    pub distance: f64,
    pub on_body: [f64; 3],
    pub on_obstacle: [f64; 3],
}

/// Outcome of the distance-field pass over a body's axis samples.
#[derive(Clone, Copy, Debug)]
pub enum SampleVerdict {
    Collides,
    Free,
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

#[derive(Clone, Debug)]
pub struct VoxelIndex {
    resolution: f64,
    inverse_resolution: f64,
    /// The region's corners in metres (for a cheap inside test).
    region: ([f64; 3], [f64; 3]),
    /// Grid coordinate (floor(x / resolution)) of cell (0, 0, 0) per axis.
    origin: [i64; 3],
    dims: [usize; 3],
    occupied: Vec<bool>,
    num_occupied: usize,
    /// What the body tests read per cell, kept together so a lookup touches one
    /// cache line.
    field: Vec<CellField>,
}

/// The distance fields at one cell.
#[derive(Clone, Copy, Debug)]
struct CellField {
    /// Linear index of the occupied cell whose centre is nearest this cell's centre
    /// (NONE if none).
    nearest: u32,
    /// Lower bounds on the distance to the nearest occupied voxel box, exact within a
    /// window of cells and clamped beyond: from the cell's centre (`box_distance`), and
    /// from anywhere in the cell (`cell_distance`, the gap between the two cells as boxes).
    box_distance: f32,
    cell_distance: f32,
}

impl CellField {
    const EMPTY: CellField = CellField {
        nearest: NONE,
        box_distance: f32::INFINITY,
        cell_distance: f32::INFINITY,
    };
}

impl VoxelIndex {
    /// An empty index covering the cube `centre ± half_extent` at `resolution`
    /// (cells aligned with the octree's: cell i spans [i·res, (i+1)·res)).
    pub fn empty(resolution: f64, centre: [f64; 3], half_extent: f64) -> Result<Self> {
        if !(resolution.is_finite() && resolution > 0.0) {
            return Err(Error::InvalidArgument(format!(
                "resolution must be finite and > 0, got {resolution}"
            )));
        }
        if !(half_extent.is_finite() && half_extent > 0.0 && centre.iter().all(|c| c.is_finite())) {
            return Err(Error::InvalidArgument(format!(
                "the index region {centre:?} ± {half_extent} is not finite"
            )));
        }
        let mut origin = [0i64; 3];
        let mut dims = [0usize; 3];
        for a in 0..3 {
            // One spare cell each side so boxes touching the region's edge are seen.
            let lo = ((centre[a] - half_extent) / resolution).floor() as i64 - 1;
            let hi = ((centre[a] + half_extent) / resolution).floor() as i64 + 1;
            origin[a] = lo;
            dims[a] = (hi - lo + 1) as usize;
        }
        let cells = dims[0] * dims[1] * dims[2];
        if cells > 64_000_000 {
            return Err(Error::InvalidArgument(format!(
                "the collision index would need {cells} cells ({:?}); use a coarser map or a smaller region",
                dims
            )));
        }
        Ok(VoxelIndex {
            resolution,
            inverse_resolution: 1.0 / resolution,
            region: (
                [0, 1, 2].map(|a| origin[a] as f64 * resolution),
                [0, 1, 2].map(|a| (origin[a] + dims[a] as i64) as f64 * resolution),
            ),
            origin,
            dims,
            occupied: vec![false; cells],
            num_occupied: 0,
            field: vec![CellField::EMPTY; cells],
        })
    }

    /// The index of `tree`'s obstacle voxels (per `source`) in the cube
    /// `centre ± half_extent`, with its distance field computed.
    pub fn from_tree(
        tree: &OcTree,
        source: VoxelSource,
        centre: [f64; 3],
        half_extent: f64,
    ) -> Result<Self> {
        let mut index = Self::empty(tree.resolution(), centre, half_extent)?;
        let to_key = |g: i64| (g + 32768).clamp(0, 65535) as u16;
        let min_key = OcTreeKey([
            to_key(index.origin[0]),
            to_key(index.origin[1]),
            to_key(index.origin[2]),
        ]);
        let max_key = OcTreeKey([
            to_key(index.origin[0] + index.dims[0] as i64 - 1),
            to_key(index.origin[1] + index.dims[1] as i64 - 1),
            to_key(index.origin[2] + index.dims[2] as i64 - 1),
        ]);
        match source {
            VoxelSource::Occupied => {
                let threshold = tree.occupancy_threshold_log_odds();
                tree.for_each_leaf_in_keys(min_key, max_key, |leaf| {
                    if leaf.log_odds > threshold {
                        let span = 1i64 << (TREE_DEPTH - leaf.depth);
                        let lo = leaf.key.0.map(|k| i64::from(k) - 32768);
                        index.mark_box(lo, [lo[0] + span - 1, lo[1] + span - 1, lo[2] + span - 1]);
                    }
                });
            }
            VoxelSource::CurrentObstacles => {
                for &m in tree.danger_map().current_obstacles() {
                    let g = OcTreeKey::from_morton(m).0.map(|k| i64::from(k) - 32768);
                    index.mark_box(g, g);
                }
            }
        }
        index.compute_distance_field();
        Ok(index)
    }

    /// Mark the grid box [lo, hi] (inclusive grid coordinates) occupied, clipped to the index.
    pub fn mark_box(&mut self, lo: [i64; 3], hi: [i64; 3]) {
        let mut a = [0usize; 3];
        let mut b = [0usize; 3];
        for i in 0..3 {
            let l = (lo[i] - self.origin[i]).max(0);
            let h = (hi[i] - self.origin[i]).min(self.dims[i] as i64 - 1);
            if l > h {
                return;
            }
            a[i] = l as usize;
            b[i] = h as usize;
        }
        for z in a[2]..=b[2] {
            for y in a[1]..=b[1] {
                for x in a[0]..=b[0] {
                    let i = self.linear([x, y, z]);
                    if !self.occupied[i] {
                        self.occupied[i] = true;
                        self.num_occupied += 1;
                    }
                }
            }
        }
    }

    /// Mark the cell holding a metric point occupied (tests, hand-built scenes).
    pub fn mark_point(&mut self, p: [f64; 3]) {
        let g = p.map(|c| (c / self.resolution).floor() as i64);
        self.mark_box(g, g);
    }

    pub fn resolution(&self) -> f64 {
        self.resolution
    }

    pub fn dims(&self) -> [usize; 3] {
        self.dims
    }

    pub fn num_occupied(&self) -> usize {
        self.num_occupied
    }

    pub fn memory_usage(&self) -> usize {
        self.occupied.len() * (1 + std::mem::size_of::<CellField>())
    }

    /// Centres of the occupied cells (for tests and pictures).
    pub fn occupied_centers(&self) -> Vec<[f64; 3]> {
        (0..self.occupied.len())
            .filter(|&i| self.occupied[i])
            .map(|i| self.center_of(i))
            .collect()
    }

    #[inline]
    fn linear(&self, c: [usize; 3]) -> usize {
        (c[2] * self.dims[1] + c[1]) * self.dims[0] + c[0]
    }

    #[inline]
    fn coords(&self, i: usize) -> [usize; 3] {
        let x = i % self.dims[0];
        let yz = i / self.dims[0];
        [x, yz % self.dims[1], yz / self.dims[1]]
    }

    /// Is a metric point inside the index? (As `cell_of` decides it, up to rounding at
    /// the region's faces, which the spare cells make harmless.)
    #[inline]
    fn contains(&self, p: &[f64; 3]) -> bool {
        let (lo, hi) = &self.region;
        (0..3).all(|a| p[a] >= lo[a] && p[a] < hi[a])
    }

    /// Cell holding a metric point, if inside the index.
    #[inline]
    fn cell_of(&self, p: &[f64; 3]) -> Option<(usize, [f64; 3])> {
        let mut c = [0usize; 3];
        let mut centre = [0.0; 3];
        for a in 0..3 {
            // Grid coordinate relative to the index; NaN fails the range test. (A point
            // within an ulp of a face may land in the neighbour: the bounds read there
            // still hold to far below the tests' 1e-6 m slack.)
            let local = p[a] * self.inverse_resolution - self.origin[a] as f64;
            if !(local >= 0.0 && local < self.dims[a] as f64) {
                return None;
            }
            c[a] = local as usize;
            centre[a] = ((self.origin[a] + c[a] as i64) as f64 + 0.5) * self.resolution;
        }
        Some((self.linear(c), centre))
    }

    #[inline]
    fn center_of(&self, i: usize) -> [f64; 3] {
        let c = self.coords(i);
        [0, 1, 2].map(|a| ((self.origin[a] + c[a] as i64) as f64 + 0.5) * self.resolution)
    }

    /// Distance transform (Felzenszwalb & Huttenlocher, separable, with the nearest
    /// site carried along): exact Euclidean distances between cell centres.
    pub fn compute_distance_field(&mut self) {
        let n = self.occupied.len();
        let mut sq: Vec<f64> = self
            .occupied
            .iter()
            .map(|&o| if o { 0.0 } else { f64::INFINITY })
            .collect();
        let mut site: Vec<u32> = (0..n)
            .map(|i| if self.occupied[i] { i as u32 } else { NONE })
            .collect();
        let longest = self.dims.into_iter().max().unwrap_or(0);
        let mut line_f = vec![0.0; longest];
        let mut line_s = vec![NONE; longest];
        let mut out_f = vec![0.0; longest];
        let mut out_s = vec![NONE; longest];
        let mut v = vec![0usize; longest];
        let mut z = vec![0.0f64; longest + 1];
        for axis in 0..3 {
            for (start, stride, len) in self.lines(axis) {
                for q in 0..len {
                    line_f[q] = sq[start + q * stride];
                    line_s[q] = site[start + q * stride];
                }
                distance_transform_1d(
                    &line_f[..len],
                    &line_s[..len],
                    &mut out_f[..len],
                    &mut out_s[..len],
                    &mut v,
                    &mut z,
                );
                for q in 0..len {
                    sq[start + q * stride] = out_f[q];
                    site[start + q * stride] = out_s[q];
                }
            }
        }
        let from_centre = self.windowed_box_distance(0.5);
        let from_cell = self.windowed_box_distance(1.0);
        self.field = (0..n)
            .map(|i| CellField {
                nearest: site[i],
                box_distance: from_centre[i],
                cell_distance: from_cell[i],
            })
            .collect();
    }

    /// The grid's lines along `axis` as (first cell, stride, length): the separable
    /// passes of the distance fields run along each in turn.
    fn lines(&self, axis: usize) -> impl Iterator<Item = (usize, usize, usize)> + '_ {
        let strides = [1, self.dims[0], self.dims[0] * self.dims[1]];
        let others: Vec<usize> = (0..3).filter(|&a| a != axis).collect();
        let (a, b) = (others[0], others[1]);
        (0..self.dims[b]).flat_map(move |j| {
            (0..self.dims[a]).map(move |i| {
                (
                    i * strides[a] + j * strides[b],
                    strides[axis],
                    self.dims[axis],
                )
            })
        })
    }

    /// Distance to the nearest occupied box within a window of `w` cells per axis:
    /// three passes of a 1D min-convolution with the per-axis gap (|n| − shift)₊²
    /// (shift ½: from the cell centre; shift 1: from the nearest point of the cell),
    /// then clamped to (w + 1 − shift)·res, below which no box outside the window comes.
    fn windowed_box_distance(&self, shift: f64) -> Vec<f32> {
        let res = self.resolution;
        let w = ((0.25 / res).ceil() as usize).clamp(2, 8);
        let gap: Vec<f64> = (0..=w)
            .map(|n| {
                let e = (n as f64 - shift).max(0.0);
                e * e
            })
            .collect();
        let mut f: Vec<f64> = self
            .occupied
            .iter()
            .map(|&o| if o { 0.0 } else { f64::INFINITY })
            .collect();
        let mut line = vec![0.0f64; self.dims.into_iter().max().unwrap_or(0)];
        for axis in 0..3 {
            for (start, stride, len) in self.lines(axis) {
                for q in 0..len {
                    line[q] = f[start + q * stride];
                }
                if line[..len].iter().all(|v| v.is_infinite()) {
                    continue;
                }
                for q in 0..len {
                    let lo = q.saturating_sub(w);
                    let hi = (q + w).min(len - 1);
                    let mut best = f64::INFINITY;
                    for (k, v) in line[lo..=hi].iter().enumerate() {
                        let n = (lo + k).abs_diff(q);
                        best = best.min(v + gap[n]);
                    }
                    f[start + q * stride] = best;
                }
            }
        }
        let cap = (w as f64 + 1.0 - shift) * res;
        f.iter()
            .map(|&v| (v.sqrt() * res).min(cap) as f32)
            .collect()
    }

    #[inline]
    fn half(&self) -> [f64; 3] {
        [0.5 * self.resolution; 3]
    }

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
        if self.num_occupied == 0 {
            return Ok(None);
        }
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

    fn outside_error(&self, p: &[f64; 3]) -> Error {
        let lo: Vec<f64> = (0..3)
            .map(|a| self.origin[a] as f64 * self.resolution)
            .collect();
        let hi: Vec<f64> = (0..3)
            .map(|a| (self.origin[a] + self.dims[a] as i64) as f64 * self.resolution)
            .collect();
        Error::InvalidArgument(format!(
            "a robot body at {p:?} lies outside the collision index region {lo:?}..{hi:?}"
        ))
    }
}

/// Squared distance from a point to an axis-aligned box.
#[inline]
fn point_box_distance_squared(p: &[f64; 3], center: &[f64; 3], half: &[f64; 3]) -> f64 {
    (0..3)
        .map(|i| {
            let e = ((p[i] - center[i]).abs() - half[i]).max(0.0);
            e * e
        })
        .sum()
}

/// Lower envelope of parabolas (q − v)² + f(v) over the sites with finite f; writes
/// the squared distance and the nearest site's label for every q.
fn distance_transform_1d(
    f: &[f64],
    label: &[u32],
    d: &mut [f64],
    out_label: &mut [u32],
    v: &mut [usize],
    z: &mut [f64],
) {
    let n = f.len();
    let Some(first) = f.iter().position(|x| x.is_finite()) else {
        d.fill(f64::INFINITY);
        out_label.fill(NONE);
        return;
    };
    let mut k = 0usize;
    v[0] = first;
    z[0] = f64::NEG_INFINITY;
    z[1] = f64::INFINITY;
    for q in first + 1..n {
        if !f[q].is_finite() {
            continue;
        }
        let fq = f[q] + (q * q) as f64;
        loop {
            let p = v[k];
            let s = (fq - (f[p] + (p * p) as f64)) / (2.0 * (q as f64 - p as f64));
            if s <= z[k] {
                // k > 0 here: z[0] = -∞ is never ≥ s.
                k -= 1;
                continue;
            }
            k += 1;
            v[k] = q;
            z[k] = s;
            z[k + 1] = f64::INFINITY;
            break;
        }
    }
    k = 0;
    for q in 0..n {
        while z[k + 1] < q as f64 {
            k += 1;
        }
        let p = v[k];
        let dq = q as f64 - p as f64;
        d[q] = dq * dq + f[p];
        out_label[q] = label[p];
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::robot::capsule::segment_box_closest;
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

    fn random_index(rng: &mut Rng, res: f64, count: usize) -> VoxelIndex {
        let mut index = VoxelIndex::empty(res, [0.0; 3], 0.6).unwrap();
        for _ in 0..count {
            index.mark_point([
                rng.uniform(-0.6, 0.6),
                rng.uniform(-0.6, 0.6),
                rng.uniform(-0.6, 0.6),
            ]);
        }
        index.compute_distance_field();
        index
    }

    #[test]
    fn distance_field_matches_brute_force() {
        let mut rng = Rng::new(5);
        let index = random_index(&mut rng, 0.1, 12);
        let occupied = index.occupied_centers();
        for i in 0..index.occupied.len() {
            let c = index.center_of(i);
            let brute = occupied
                .iter()
                .map(|o| crate::geometry::distance_squared(o, &c).sqrt())
                .fold(f64::INFINITY, f64::min);
            let near = index.center_of(index.field[i].nearest as usize);
            assert!((crate::geometry::distance_squared(&near, &c).sqrt() - brute).abs() < 1e-9);
        }
    }

    #[test]
    fn box_distance_is_a_tight_lower_bound() {
        let mut rng = Rng::new(6);
        let index = random_index(&mut rng, 0.05, 30);
        let occupied = index.occupied_centers();
        let half = index.half();
        for i in 0..index.occupied.len() {
            let c = index.center_of(i);
            let brute = occupied
                .iter()
                .map(|o| point_box_distance_squared(&c, o, &half).sqrt())
                .fold(f64::INFINITY, f64::min);
            let got = index.field[i].box_distance as f64;
            assert!(got <= brute + 1e-6, "{got} > {brute}");
            if brute < 0.25 {
                assert!((got - brute).abs() < 1e-6, "{got} vs {brute}");
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
