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
    // Work cell by cell: the points of one cell share their 27-cell candidate list.
    let cell_list: Vec<CellRange> = grid.cells.iter().map(|(&c, &r)| (c, r)).collect();
    let chunks: Vec<&[CellRange]> = cell_list.chunks(256).collect();
    let parts = threads::map_parts(&chunks, |chunk| {
        let mut block: Vec<([f64; 3], u32)> = Vec::new();
        let mut candidates: Vec<f64> = Vec::new();
        let mut nn = Vec::with_capacity(k);
        let mut results: Vec<(u32, f64)> = Vec::new();
        for &(c, (s, e)) in chunk.iter() {
            grid.block(points, c, &mut block);
            for &i in &grid.order[s as usize..e as usize] {
                let q = points[i as usize];
                candidates.clear();
                candidates.extend(
                    block
                        .iter()
                        .filter(|&&(_, j)| j != i)
                        .map(|(p, _)| crate::geometry::distance_squared(p, &q)),
                );
                let mut mean = None;
                if candidates.len() >= k {
                    let (_, kth_d2, _) = candidates.select_nth_unstable_by(k - 1, f64::total_cmp);
                    if kth_d2.sqrt() <= cell {
                        mean = Some(
                            candidates[..k].iter().map(|d2| d2.sqrt()).sum::<f64>() / k as f64,
                        );
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

/// Points bucketed by cell: `order[start..end]` of a cell's range are its points.
struct Grid {
    cells: rustc_hash::FxHashMap<[i64; 3], (u32, u32)>,
    order: Vec<u32>,
}

impl Grid {
    fn new(points: &[[f64; 3]], cell: f64) -> Self {
        let inv = 1.0 / cell;
        let key = |p: &[f64; 3]| cell_of(p, inv);
        let mut keyed: Vec<([i64; 3], u32)> = points
            .iter()
            .enumerate()
            .map(|(i, p)| (key(p), i as u32))
            .collect();
        keyed.sort_unstable();
        let mut cells = rustc_hash::FxHashMap::default();
        let mut start = 0;
        while start < keyed.len() {
            let mut end = start + 1;
            while end < keyed.len() && keyed[end].0 == keyed[start].0 {
                end += 1;
            }
            cells.insert(keyed[start].0, (start as u32, end as u32));
            start = end;
        }
        Grid {
            cells,
            order: keyed.into_iter().map(|(_, i)| i).collect(),
        }
    }

    /// The points (position, index) of the 3×3×3 block of cells around cell `c`.
    fn block(&self, points: &[[f64; 3]], c: [i64; 3], out: &mut Vec<([f64; 3], u32)>) {
        out.clear();
        for dz in -1..=1 {
            for dy in -1..=1 {
                for dx in -1..=1 {
                    if let Some(&(s, e)) = self.cells.get(&[c[0] + dx, c[1] + dy, c[2] + dz]) {
                        out.extend(
                            self.order[s as usize..e as usize]
                                .iter()
                                .map(|&j| (points[j as usize], j)),
                        );
                    }
                }
            }
        }
    }
}
