//! Statistical outlier removal, as PCL defines it: for every point the mean distance
//! to its k nearest neighbours (itself excluded); a point is an outlier when that mean
//! exceeds μ + std_ratio·σ over all points (σ the sample standard deviation).

use super::kdtree::KdTree;
use crate::error::{Error, Result};
use crate::floor::cell_of;
use crate::threads;

#[derive(Clone, Copy, Debug, PartialEq)]
pub struct OutlierParams {
    /// Neighbours per point.
    pub k: usize,
    /// How many standard deviations above the mean a point's distance may be.
    pub std_ratio: f64,
}

impl Default for OutlierParams {
    fn default() -> Self {
        OutlierParams {
            k: 20,
            std_ratio: 2.0,
        }
    }
}

/// Indices of the inliers (ascending) and every point's mean neighbour distance.
pub fn statistical_outliers(
    points: &[[f64; 3]],
    params: OutlierParams,
) -> Result<(Vec<u32>, Vec<f64>)> {
    if params.k == 0 || !params.std_ratio.is_finite() {
        return Err(Error::InvalidArgument(format!(
            "need k >= 1 and a finite std_ratio, got {params:?}"
        )));
    }
    if points.len() <= params.k {
        return Err(Error::InvalidArgument(format!(
            "statistical outlier removal needs more points than k = {} neighbours, got {}",
            params.k,
            points.len()
        )));
    }
    crate::geometry::check_finite(points, "point")?;
    let mean_distance = mean_knn_distances(points, params.k);
    let n = mean_distance.len() as f64;
    let mean = mean_distance.iter().sum::<f64>() / n;
    let variance = mean_distance
        .iter()
        .map(|d| (d - mean).powi(2))
        .sum::<f64>()
        / (n - 1.0);
    let threshold = mean + params.std_ratio * variance.sqrt();
    let inliers = (0..points.len() as u32)
        .filter(|&i| mean_distance[i as usize] <= threshold)
        .collect();
    Ok((inliers, mean_distance))
}

/// Every point's mean distance to its `k` nearest neighbours (itself excluded).
///
/// A uniform grid does most of the work: with cells of edge `s`, the candidates of a
/// point are the points of its 3×3×3 block of cells, and any point outside that block
/// is at least `s` away; so when the k-th nearest candidate lies within `s`, the
/// candidates hold the exact k nearest distances. The rest (sparse regions) ask a
/// k-d tree. `s` is the 90th percentile of the k-th neighbour distance of a sample.
///
/// Per point, only candidates within a guess of its k-th distance (the previous
/// point's, which a neighbour shares closely) go to the selection; the guess widens
/// until at least k of them pass. The point itself is a candidate (distance 0, the
/// smallest), so the k + 1 smallest hold exactly its k nearest distances.
fn mean_knn_distances(points: &[[f64; 3]], k: usize) -> Vec<f64> {
    let tree = KdTree::new(points);
    let mut out = Vec::with_capacity(k);
    let kth = |i: usize, out: &mut Vec<(f64, u32)>| {
        tree.knn(points[i], k, Some(i as u32), out);
        out.last().map_or(0.0, |&(d2, _)| d2.sqrt())
    };
    let step = (points.len() / 64).max(1);
    let mut sample: Vec<f64> = (0..points.len())
        .step_by(step)
        .map(|i| kth(i, &mut out))
        .collect();
    sample.sort_unstable_by(f64::total_cmp);
    let cell = sample[(sample.len() * 9 / 10).min(sample.len() - 1)].max(1e-12);
    let grid = Grid::new(points, cell);
    let chunks: Vec<&[CellRange]> = grid.cells.chunks(256).collect();
    let parts = threads::map_parts(&chunks, |chunk| {
        let mut block = Block::default();
        let mut near: Vec<u64> = Vec::new();
        let mut d2: Vec<f64> = Vec::new();
        let mut nn = Vec::with_capacity(k);
        let mut results: Vec<(u32, f64)> = Vec::new();
        let mut guess = cell * cell;
        for &(c, (s, e)) in chunk.iter() {
            grid.block(c, &mut block);
            for &i in &grid.order[s as usize..e as usize] {
                let q = points[i as usize];
                let mut mean = None;
                if block.len() > k {
                    // Everything outside the block is farther than the nearest block face.
                    let reach = (0..3)
                        .map(|a| {
                            let lo = (c[a] - 1) as f64 * cell;
                            let hi = (c[a] + 2) as f64 * cell;
                            (q[a] - lo).min(hi - q[a])
                        })
                        .fold(f64::INFINITY, f64::min);
                    let proven = reach * reach;
                    // The floor keeps the widening going after a guess of 0 (a point
                    // with k copies of itself).
                    let mut t = guess.max(1e-4 * cell * cell).min(proven);
                    block.distances(q, &mut d2);
                    loop {
                        at_most(&d2, t, &mut near);
                        if near.len() > k || t >= proven {
                            break;
                        }
                        t = (t * 2.25).min(proven);
                    }
                    if near.len() > k {
                        // Non-negative doubles order as their bit patterns.
                        keep_smallest(&mut near, k + 1);
                        let kth_d2 = f64::from_bits(near.iter().copied().max().unwrap_or(0));
                        guess = kth_d2 * 1.3;
                        let sum: f64 = near.iter().map(|&b| f64::from_bits(b).sqrt()).sum();
                        mean = Some(sum / k as f64);
                    }
                }
                let mean = mean.unwrap_or_else(|| {
                    tree.knn(q, k, Some(i), &mut nn);
                    nn.iter().map(|&(d2, _)| d2.sqrt()).sum::<f64>() / nn.len() as f64
                });
                results.push((i, mean));
            }
        }
        results
    });
    let mut mean_distance = vec![0.0; points.len()];
    for (i, m) in parts.into_iter().flatten() {
        mean_distance[i as usize] = m;
    }
    mean_distance
}

/// A cell's coordinates and the range of its points in `Grid::order`.
type CellRange = ([i64; 3], (u32, u32));

/// Points bucketed by cell, cells in lexicographic order of their coordinates:
/// `order[start..end]` of a cell's range are its points, `coords` their positions
/// in the same order (a column of cells along z is one contiguous run).
struct Grid {
    cells: Vec<CellRange>,
    index: rustc_hash::FxHashMap<[i64; 3], u32>,
    order: Vec<u32>,
    coords: [Vec<f64>; 3],
}

impl Grid {
    fn new(points: &[[f64; 3]], cell: f64) -> Self {
        let inv = 1.0 / cell;
        let mut keyed: Vec<([i64; 3], u32)> = points
            .iter()
            .enumerate()
            .map(|(i, p)| (cell_of(p, inv), i as u32))
            .collect();
        keyed.sort_unstable();
        let mut cells = Vec::new();
        let mut start = 0;
        while start < keyed.len() {
            let mut end = start + 1;
            while end < keyed.len() && keyed[end].0 == keyed[start].0 {
                end += 1;
            }
            cells.push((keyed[start].0, (start as u32, end as u32)));
            start = end;
        }
        let index = cells
            .iter()
            .enumerate()
            .map(|(n, &(c, _))| (c, n as u32))
            .collect();
        let order: Vec<u32> = keyed.into_iter().map(|(_, i)| i).collect();
        let coords = [0, 1, 2].map(|a| order.iter().map(|&i| points[i as usize][a]).collect());
        Grid {
            cells,
            index,
            order,
            coords,
        }
    }

    /// The positions of the points in the 3×3×3 block of cells around cell `c`.
    fn block(&self, c: [i64; 3], out: &mut Block) {
        for a in &mut out.coords {
            a.clear();
        }
        for dx in -1..=1 {
            for dy in -1..=1 {
                // The present cells of a z-column are neighbours in `cells`.
                let column =
                    (-1..=1).filter_map(|dz| self.index.get(&[c[0] + dx, c[1] + dy, c[2] + dz]));
                let (mut first, mut last) = (u32::MAX, 0);
                for &n in column {
                    first = first.min(n);
                    last = last.max(n);
                }
                if first == u32::MAX {
                    continue;
                }
                let (s, e) = (
                    self.cells[first as usize].1 .0,
                    self.cells[last as usize].1 .1,
                );
                for a in 0..3 {
                    out.coords[a].extend_from_slice(&self.coords[a][s as usize..e as usize]);
                }
            }
        }
    }
}

/// Candidate positions, one array per axis (the distance loop vectorises).
#[derive(Default)]
struct Block {
    coords: [Vec<f64>; 3],
}

impl Block {
    fn len(&self) -> usize {
        self.coords[0].len()
    }

    /// The squared distances from `q` to every candidate.
    fn distances(&self, q: [f64; 3], out: &mut Vec<f64>) {
        let [xs, ys, zs] = &self.coords;
        out.clear();
        out.extend(xs.iter().zip(ys).zip(zs).map(|((&x, &y), &z)| {
            (x - q[0]) * (x - q[0]) + (y - q[1]) * (y - q[1]) + (z - q[2]) * (z - q[2])
        }));
    }
}

/// Reorders `v` so that its `n` smallest values come first, and truncates to them.
/// Usually only a few values are too many: dropping the largest one at a time beats
/// a general selection there.
fn keep_smallest(v: &mut Vec<u64>, n: usize) {
    if v.len() > n + 8 {
        v.select_nth_unstable(n - 1);
    } else {
        while v.len() > n {
            let (at, _) =
                v.iter().enumerate().fold(
                    (0, 0),
                    |best, (i, &x)| if x >= best.1 { (i, x) } else { best },
                );
            v.swap_remove(at);
        }
    }
    v.truncate(n);
}

/// The values of `d2` that are at most `t`, as bit patterns (which order as the
/// values do, all being non-negative).
#[inline(never)] // keeps `t` in a register: inlined, it was reloaded after every store
fn at_most(d2: &[f64], t: f64, out: &mut Vec<u64>) {
    out.clear();
    out.resize(d2.len(), 0);
    let slots = out.as_mut_slice();
    let mut n = 0;
    for (i, &d) in d2.iter().enumerate() {
        // Branch-free compaction: write always, advance only when it counts.
        // n <= i < slots.len(), so the index is in bounds; `min` lets the compiler see it.
        slots[n.min(i)] = d.to_bits();
        n += usize::from(d <= t);
    }
    out.truncate(n);
}
