//! Statistical outlier removal, as PCL defines it: for every point the mean distance
//! to its k nearest neighbours (itself excluded); a point is an outlier when that mean
//! exceeds μ + std_ratio·σ over all points (σ the sample standard deviation).

use super::kdtree::KdTree;
use crate::error::{Error, Result};
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
    if let Some(i) = points.iter().position(|p| !p.iter().all(|c| c.is_finite())) {
        return Err(Error::InvalidArgument(format!(
            "point {i} {:?} is not finite",
            points[i]
        )));
    }
    let tree = KdTree::new(points);
    const CHUNK: usize = 4096;
    let starts: Vec<usize> = (0..points.len()).step_by(CHUNK).collect();
    let parts = threads::map_parts(&starts, |&start| {
        let mut out = Vec::with_capacity(params.k);
        (start..(start + CHUNK).min(points.len()))
            .map(|i| {
                tree.knn(points[i], params.k, Some(i as u32), &mut out);
                out.iter().map(|&(d2, _)| d2.sqrt()).sum::<f64>() / out.len() as f64
            })
            .collect::<Vec<f64>>()
    });
    let mean_distance: Vec<f64> = parts.concat();
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
