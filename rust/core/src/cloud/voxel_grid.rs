//! Voxel-grid down-sampling: the points of every occupied voxel (a grid of edge
//! `voxel_size` anchored at the origin) are replaced by their centroid; optional
//! per-point values (colours, normals...) are averaged the same way.

use std::hash::Hash;

use rustc_hash::FxHashMap;

use crate::error::{Error, Result};
use crate::floor::floor_i64;

/// Packed keys hold cells -2^20..2^20 per axis, 21 bits each in one u64.
const PACKED_OFFSET: i64 = 1 << 20;

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
    crate::geometry::check_finite(points, "point")?;
    let inv = 1.0 / voxel_size;
    // A u64 key hashes and compares faster, and halves the table (it stays in cache);
    // cells beyond its span (±2^20 per axis) take the general key.
    let packed = accumulate(points, values, inv, |c| {
        let [x, y, z] = c.map(|v| (v + PACKED_OFFSET) as u64);
        ((x | y | z) < 1 << 21).then_some(x << 42 | y << 21 | z)
    });
    Ok(packed.unwrap_or_else(|| {
        accumulate(points, values, inv, Some).expect("every cell has a general key")
    }))
}

/// Sums per voxel, in order of each voxel's first point, then means; `None` as soon
/// as a cell has no key.
fn accumulate<K: Copy + Eq + Hash>(
    points: &[[f64; 3]],
    values: Option<(&[f64], usize)>,
    inv: f64,
    key_of: impl Fn([i64; 3]) -> Option<K>,
) -> Option<(Vec<[f64; 3]>, Vec<f64>)> {
    // Room for a voxel per 8 points from the start: growing the table rehashes it.
    let mut slot_of: FxHashMap<K, u32> =
        FxHashMap::with_capacity_and_hasher(points.len() / 8, Default::default());
    // Per voxel the sums of x, y and z and the number of points.
    let mut voxels: Vec<[f64; 4]> = Vec::new();
    // Every point's voxel, kept only when values are averaged too.
    let mut slots: Vec<u32> = Vec::with_capacity(if values.is_some() { points.len() } else { 0 });
    // The current voxel as [lo, lo + 1) in cell units per axis (NaN: none yet).
    // Points of a depth image come row by row: the previous point's voxel is often
    // this one's too, and two comparisons per axis are cheaper than a key and a hash.
    let mut lo = [f64::NAN; 3];
    let mut hi = [f64::NAN; 3];
    let mut slot = 0;
    for p in points {
        let v = [p[0] * inv, p[1] * inv, p[2] * inv];
        let inside = (v[0] >= lo[0])
            & (v[0] < hi[0])
            & (v[1] >= lo[1])
            & (v[1] < hi[1])
            & (v[2] >= lo[2])
            & (v[2] < hi[2]);
        if !inside {
            let cell = v.map(floor_i64);
            let next = voxels.len() as u32;
            slot = *slot_of.entry(key_of(cell)?).or_insert(next) as usize;
            if slot == voxels.len() {
                voxels.push([0.0; 4]);
            }
            lo = cell.map(|c| c as f64);
            hi = lo.map(|c| c + 1.0);
        }
        let sums = &mut voxels[slot];
        sums[0] += p[0];
        sums[1] += p[1];
        sums[2] += p[2];
        sums[3] += 1.0;
        if values.is_some() {
            slots.push(slot as u32);
        }
    }
    let centroids = voxels
        .iter()
        .map(|s| [s[0] / s[3], s[1] / s[3], s[2] / s[3]])
        .collect();
    let means = match values {
        None => Vec::new(),
        Some((v, stride)) => {
            let mut sums = vec![0.0; voxels.len() * stride];
            for (row, &slot) in v.chunks_exact(stride.max(1)).zip(&slots) {
                let at = slot as usize * stride;
                for (sum, x) in sums[at..at + stride].iter_mut().zip(row) {
                    *sum += x;
                }
            }
            for (voxel, sums) in voxels.iter().zip(sums.chunks_exact_mut(stride.max(1))) {
                for x in sums {
                    *x /= voxel[3];
                }
            }
            sums
        }
    };
    Some((centroids, means))
}
