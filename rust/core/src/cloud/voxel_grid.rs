//! Voxel-grid down-sampling: the points of every occupied voxel (a grid of edge
//! `voxel_size` anchored at the origin) are replaced by their centroid; optional
//! per-point values (colours, normals...) are averaged the same way.

use rustc_hash::FxHashMap;

use crate::error::{Error, Result};
use crate::floor::cell_of;

/// Returns the centroids (in order of each voxel's first point) and, when `values`
/// (`stride` numbers per point) are given, their per-voxel means.
pub fn voxel_downsample(
    points: &[[f64; 3]],
    voxel_size: f64,
    values: Option<(&[f64], usize)>,
) -> Result<(Vec<[f64; 3]>, Vec<f64>)> {
    if !(voxel_size.is_finite() && voxel_size > 0.0) {
        return Err(Error::InvalidArgument(format!(
            "voxel_size must be a positive length, got {voxel_size}"
        )));
    }
    let stride = values.map_or(0, |(_, s)| s);
    if let Some((v, s)) = values {
        if v.len() != points.len() * s {
            return Err(Error::InvalidArgument(format!(
                "values must have one row per point ({} rows of {s})",
                points.len()
            )));
        }
    }
    let inv = 1.0 / voxel_size;
    let mut slot_of: FxHashMap<[i64; 3], u32> = FxHashMap::default();
    let mut sums: Vec<[f64; 3]> = Vec::new();
    let mut counts: Vec<u32> = Vec::new();
    let mut value_sums: Vec<f64> = Vec::new();
    for (i, p) in points.iter().enumerate() {
        if !p.iter().all(|c| c.is_finite()) {
            return Err(Error::InvalidArgument(format!(
                "point {i} {p:?} is not finite"
            )));
        }
        let next = sums.len() as u32;
        let slot = *slot_of.entry(cell_of(p, inv)).or_insert(next) as usize;
        if slot == sums.len() {
            sums.push([0.0; 3]);
            counts.push(0);
            value_sums.resize(value_sums.len() + stride, 0.0);
        }
        for a in 0..3 {
            sums[slot][a] += p[a];
        }
        counts[slot] += 1;
        if let Some((v, s)) = values {
            for j in 0..s {
                value_sums[slot * s + j] += v[i * s + j];
            }
        }
    }
    let centroids = sums
        .iter()
        .zip(&counts)
        .map(|(s, &c)| s.map(|x| x / f64::from(c)))
        .collect();
    for (slot, &c) in counts.iter().enumerate() {
        for j in 0..stride {
            value_sums[slot * stride + j] /= f64::from(c);
        }
    }
    Ok((centroids, value_sums))
}
