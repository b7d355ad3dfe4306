//! A dense index of a map's occupied voxels around the robot, with a Euclidean
//! distance transform (distance from every cell centre to the nearest occupied cell
//! centre, and which cell that is), for fast conservative capsule tests and clearance.
//!
//! Capsule tests walk sample points along the capsule's axis: a sample whose cell is
//! far enough from every occupied cell proves its part of the capsule free, a sample
//! whose nearest occupied box lies within the radius proves a collision, and anything
//! in between falls back to exact segment–box tests over the capsule's cells. So the
//! answer is exact; the distance field only makes it fast.
//!
//! One concept per file: the dense grid here, the distance transform
//! (`distance_field`), the windowed box-distance bounds (`box_bounds`), the body
//! tests (`body_check`) and clearance (`clearance`).

mod body_check;
mod box_bounds;
mod clearance;
mod distance_field;

pub use body_check::{SampleVerdict, UndecidedRuns};
pub use clearance::{Clearance, ClearanceScratch};

use crate::error::{Error, Result};
use crate::octree::{OcTree, OcTreeKey, TREE_DEPTH};

const NONE: u32 = u32::MAX;

/// Most cells a collision index may hold (13 bytes each: 832 MB at the limit).
pub const MAX_INDEX_CELLS: usize = 64_000_000;

/// Which voxels of the map count as obstacles.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum VoxelSource {
    /// Every occupied leaf of the occupancy map.
    Occupied,
    /// Only the cells hit in the last closed danger frame (what the cameras see now).
    CurrentObstacles,
}

/// A dense grid of a map's obstacle voxels in a cube around the robot, with its
/// distance fields: exact body–voxel collision tests and clearance (see the module
/// documentation).
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
        // Grid coordinates in floating point first: integer casts saturate (and their
        // differences wrap) for regions far beyond what a cell count can hold.
        let mut grid = [(0.0f64, 0.0f64); 3];
        for (a, g) in grid.iter_mut().enumerate() {
            // One spare cell each side so boxes touching the region's edge are seen.
            *g = (
                ((centre[a] - half_extent) / resolution).floor() - 1.0,
                ((centre[a] + half_extent) / resolution).floor() + 1.0,
            );
        }
        let cells_f: f64 = grid.iter().map(|(lo, hi)| hi - lo + 1.0).product();
        // Grid coordinates beyond 2^52 lose whole cells to rounding.
        let representable = grid
            .iter()
            .all(|(lo, hi)| lo.abs() < 4.5e15 && hi.abs() < 4.5e15);
        if !(representable && cells_f <= MAX_INDEX_CELLS as f64) {
            let per_axis = 2.0 * half_extent / resolution;
            return Err(Error::InvalidArgument(format!(
                "the collision index of the cube {centre:.3?} ± {half_extent:.3} m at {resolution} m \
                 would need about {per_axis:.3e} cells per axis, more than {MAX_INDEX_CELLS} cells \
                 in all; use a coarser map, a smaller index_margin or a robot base within the map"
            )));
        }
        let mut origin = [0i64; 3];
        let mut dims = [0usize; 3];
        for a in 0..3 {
            origin[a] = grid[a].0 as i64;
            dims[a] = (grid[a].1 - grid[a].0) as usize + 1;
        }
        let cells = dims[0] * dims[1] * dims[2];
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

    /// Edge length of a cell, in metres.
    pub fn resolution(&self) -> f64 {
        self.resolution
    }

    /// Cells along x, y and z.
    pub fn dims(&self) -> [usize; 3] {
        self.dims
    }

    /// Number of occupied cells.
    pub fn num_occupied(&self) -> usize {
        self.num_occupied
    }

    /// Bytes of the grid and its distance fields.
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

    #[inline]
    fn half(&self) -> [f64; 3] {
        [0.5 * self.resolution; 3]
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

#[cfg(test)]
mod tests {
    use super::*;
    use crate::synthetic::Rng;

    /// An index of `count` random cells in the cube ±0.6 m, distance field computed.
    pub(super) fn random_index(rng: &mut Rng, res: f64, count: usize) -> VoxelIndex {
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
}
