//! Voxel-grid down-sampling: the points of every occupied voxel (a grid of edge
//! `voxel_size` anchored at the origin) are replaced by their centroid; optional
//! per-point values (colours, normals...) are averaged the same way.

use std::hash::Hash;

use rustc_hash::FxHashMap;

use crate::error::{Error, Result};
use crate::floor::cell_of;

/// Cells per axis a packed key can tell apart (21 bits each in one u64).
const PACKED_SPAN: i64 = 1 << 21;

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
    if let Some((v, s)) = values {
        if v.len() != points.len() * s {
            return Err(Error::InvalidArgument(format!(
                "values must have one row per point ({} rows of {s})",
                points.len()
            )));
        }
    }
    if let Some(i) = points.iter().position(|p| !p.iter().all(|c| c.is_finite())) {
        return Err(Error::InvalidArgument(format!(
            "point {i} {:?} is not finite",
            points[i]
        )));
    }
    let inv = 1.0 / voxel_size;
    let mut lo = [i64::MAX; 3];
    let mut hi = [i64::MIN; 3];
    for p in points {
        let c = cell_of(p, inv);
        for a in 0..3 {
            lo[a] = lo[a].min(c[a]);
            hi[a] = hi[a].max(c[a]);
        }
    }
    // A u64 key hashes and compares faster, and halves the table (it stays in cache).
    let packs = (0..3).all(|a| hi[a].saturating_sub(lo[a]) < PACKED_SPAN);
    if packs {
        accumulate(points, values, |p| {
            let c = cell_of(p, inv);
            ((c[0] - lo[0]) as u64) << 42 | ((c[1] - lo[1]) as u64) << 21 | (c[2] - lo[2]) as u64
        })
    } else {
        accumulate(points, values, |p| cell_of(p, inv))
    }
}

/// Sums per key, in order of each key's first point, then means.
fn accumulate<K: Copy + Eq + Hash>(
    points: &[[f64; 3]],
    values: Option<(&[f64], usize)>,
    key_of: impl Fn(&[f64; 3]) -> K,
) -> Result<(Vec<[f64; 3]>, Vec<f64>)> {
    let stride = values.map_or(0, |(_, s)| s);
    let mut slot_of: FxHashMap<K, u32> = FxHashMap::default();
    let mut sums: Vec<[f64; 3]> = Vec::new();
    let mut counts: Vec<u32> = Vec::new();
    let mut value_sums: Vec<f64> = Vec::new();
    let mut last: Option<(K, usize)> = None;
    for (i, p) in points.iter().enumerate() {
        let key = key_of(p);
        // Points of a depth image come row by row: the previous point's voxel is
        // often this one's too, and comparing keys is cheaper than hashing them.
        let slot = if let Some((_, slot)) = last.filter(|(k, _)| *k == key) {
            slot
        } else {
            let next = sums.len() as u32;
            let slot = *slot_of.entry(key).or_insert(next) as usize;
            last = Some((key, slot));
            slot
        };
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
