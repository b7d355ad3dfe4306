//! Voxel-grid down-sampling: the points of every occupied voxel (a grid of edge
//! `voxel_size` anchored at the origin) are replaced by their centroid; optional
//! per-point values (colours, normals...) are averaged the same way.

use std::hash::Hash;

use rustc_hash::FxHashMap;

use crate::error::{Error, Result};
use crate::floor::floor_i64;

/// Packed keys hold cells −2^20 ≤ c < 2^20 per axis, 21 bits each in one u64.
const PACKED_OFFSET: i64 = 1 << 20;

/// One integer per grid cell: 21 bits per axis, `(x + 2^20) << 42 | (y + 2^20) << 21 |
/// (z + 2^20)`; `None` for cells outside −2^20 ≤ c < 2^20 on some axis.
#[inline]
pub fn pack_cell(cell: [i64; 3]) -> Option<u64> {
    let [x, y, z] = cell.map(|v| v.wrapping_add(PACKED_OFFSET) as u64);
    ((x | y | z) < 1 << 21).then_some(x << 42 | y << 21 | z)
}

/// The packed cell ([`pack_cell`]) of each point on a grid of edge `resolution`
/// anchored at the origin, cell `floor(p / resolution)` per axis: one integer per
/// voxel, for set operations on voxels. Points must be finite and their cells within
/// 2^20 of the origin (|cell| < 2^20 on every axis, so no two cells share a code).
pub fn voxel_codes(points: &[[f64; 3]], resolution: f64) -> Result<Vec<i64>> {
    codes_of(points, resolution, "points")
}

/// [`voxel_codes`], naming the argument `what` in its errors.
fn codes_of(points: &[[f64; 3]], resolution: f64, what: &str) -> Result<Vec<i64>> {
    if !(resolution.is_finite() && resolution > 0.0) {
        return Err(Error::InvalidArgument(format!(
            "resolution must be finite and > 0, got {resolution}"
        )));
    }
    points
        .iter()
        .enumerate()
        .map(|(i, p)| {
            cell_code(p, resolution).ok_or_else(|| {
                Error::InvalidArgument(format!(
                    "{what} must be finite and within 2^20 cells of size {resolution} of the origin ({what}[{i}] = {p:?})"
                ))
            })
        })
        .collect()
}

/// The packed cell of `p` (cell `floor(p / resolution)`), or `None` for a non-finite
/// point or one whose cell lies 2^20 or more from the origin on some axis.
fn cell_code(p: &[f64; 3], resolution: f64) -> Option<i64> {
    const LIMIT: f64 = (1u64 << 20) as f64;
    let cell = p.map(|c| (c / resolution).floor());
    cell.iter()
        .all(|c| c.abs() < LIMIT)
        .then(|| pack_cell(cell.map(|c| c as i64)).expect("cells within ±2^20 pack") as i64)
}

/// Per voxel named by a point inside it (`centres`, typically voxel centres, on the
/// grid of [`voxel_codes`]), the mean of the `points` that fall in that voxel, or the
/// centre itself where none does. Errors like [`voxel_codes`] on a bad resolution or
/// centre, and on a non-finite point (finite points beyond the grid lie in no voxel).
pub fn voxel_means(
    centres: &[[f64; 3]],
    points: &[[f64; 3]],
    resolution: f64,
) -> Result<Vec<[f64; 3]>> {
    let codes = codes_of(centres, resolution, "centres")?;
    let mut slot_of: FxHashMap<i64, u32> = FxHashMap::default();
    slot_of.reserve(codes.len());
    let slots: Vec<u32> = codes
        .iter()
        .map(|&c| {
            let fresh = slot_of.len() as u32;
            *slot_of.entry(c).or_insert(fresh)
        })
        .collect();
    let mut sums = vec![([0.0f64; 3], 0u32); slot_of.len()];
    for (i, p) in points.iter().enumerate() {
        if !p.iter().all(|c| c.is_finite()) {
            return Err(Error::InvalidArgument(format!(
                "points must be finite (points[{i}] = {p:?})"
            )));
        }
        // A finite point beyond the grid lies in none of the voxels.
        let Some(code) = cell_code(p, resolution) else {
            continue;
        };
        if let Some(&slot) = slot_of.get(&code) {
            let (sum, count) = &mut sums[slot as usize];
            for a in 0..3 {
                sum[a] += p[a];
            }
            *count += 1;
        }
    }
    Ok(centres
        .iter()
        .zip(&slots)
        .map(|(centre, &slot)| {
            let (sum, count) = sums[slot as usize];
            if count == 0 {
                *centre
            } else {
                sum.map(|v| v / count as f64)
            }
        })
        .collect())
}

/// Returns the centroids (in order of each voxel's first point) and, when `values`
/// (`stride` numbers per point) are given, their per-voxel means. Errors when
/// `voxel_size` is not a positive length, a point is not finite or beyond the grid's
/// reach, or `values` does not hold `stride` numbers per point.
///
/// ```
/// use earcore_core::cloud::voxel_downsample;
///
/// // Two points share the voxel [0, 0.1)³; one lies alone in the next voxel along x.
/// let points = [[0.01, 0.02, 0.03], [0.03, 0.04, 0.05], [0.15, 0.0, 0.0]];
/// let (centroids, _) = voxel_downsample(&points, 0.1, None)?;
/// assert_eq!(centroids.len(), 2);
/// assert!((centroids[0][0] - 0.02).abs() < 1e-12 && (centroids[0][2] - 0.04).abs() < 1e-12);
/// assert_eq!(centroids[1], [0.15, 0.0, 0.0]);
/// // Per-point values (here one number per point) are averaged the same way.
/// let (_, means) = voxel_downsample(&points, 0.1, Some((&[1.0, 3.0, 5.0], 1)))?;
/// assert_eq!(means, [2.0, 5.0]);
/// # Ok::<(), earcore_core::Error>(())
/// ```
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
                "values must have one row per point: {} points, but {} values in rows of {s}",
                points.len(),
                v.len()
            )));
        }
    }
    crate::geometry::check_finite(points, "point")?;
    crate::geometry::check_cell_range(points, voxel_size, "voxel_size")?;
    let inv = 1.0 / voxel_size;
    // Most clouds (a cropped camera frame) span a box small enough for a table of
    // bricks of cells: two array reads find a voxel, with no hash and no shortcut
    // branch to mispredict (1.55 ms instead of 2.05 on a frame). Wider clouds hash their cells: a u64 key (±2^20 cells per axis) hashes
    // and compares faster than the general one.
    if let Some(done) =
        Bricks::covering(points, inv).and_then(|b| accumulate(points, values, inv, b))
    {
        return Ok(done);
    }
    let packed = Hashed::new(points.len(), pack_cell);
    Ok(accumulate(points, values, inv, packed).unwrap_or_else(|| {
        accumulate(points, values, inv, Hashed::new(points.len(), Some))
            .expect("every cell has a general key")
    }))
}

/// Where each voxel's sums live: a slot per cell, handed out in order of first use.
trait Slots {
    /// Whether a lookup costs less than a mispredicted branch: then every point looks
    /// its cell up; otherwise a point first tries the previous point's voxel.
    const CHEAP: bool;

    /// The slot of `cell`, or `fresh` for a cell seen for the first time; `None`
    /// when this index cannot hold the cell.
    fn slot(&mut self, cell: [i64; 3], fresh: u32) -> Option<u32>;
}

/// Cells hashed by a key.
struct Hashed<K, F> {
    slot_of: FxHashMap<K, u32>,
    key_of: F,
}

impl<K, F> Hashed<K, F> {
    fn new(points: usize, key_of: F) -> Self {
        // Room for a voxel per 8 points from the start: growing the table rehashes it.
        Hashed {
            slot_of: FxHashMap::with_capacity_and_hasher(points / 8, Default::default()),
            key_of,
        }
    }
}

impl<K: Copy + Eq + Hash, F: Fn([i64; 3]) -> Option<K>> Slots for Hashed<K, F> {
    const CHEAP: bool = false;

    fn slot(&mut self, cell: [i64; 3], fresh: u32) -> Option<u32> {
        Some(*self.slot_of.entry((self.key_of)(cell)?).or_insert(fresh))
    }
}

/// Cells in bricks of 8×8×8 over the points' bounding box: a dense table of bricks,
/// a brick's 512 slots allocated when a point first falls into it.
struct Bricks {
    /// The cell coordinates of the box's first brick's first cell.
    origin: [i64; 3],
    /// Bricks per axis.
    dims: [i64; 3],
    /// Per brick: its block in `slots`, or `NONE`.
    blocks: Vec<u32>,
    slots: Vec<u32>,
    /// Slots allowed before the bricks give up (sparse clouds: a brick per point).
    budget: usize,
}

const NONE: u32 = u32::MAX;

impl Bricks {
    /// `None` when the box needs more than 4 bricks per point (or 4096), or its cells
    /// are too many to count exactly. Points that turn out to be sparse within the box
    /// (more than 16 slots per point) make `slot` give up too.
    fn covering(points: &[[f64; 3]], inv: f64) -> Option<Self> {
        let (lo, hi) = crate::geometry::bounds(points);
        if !(0..3).all(|a| (lo[a] * inv).abs() < 1e15 && (hi[a] * inv).abs() < 1e15) {
            return None; // also an empty cloud (infinite bounds)
        }
        // The product p·inv rounds monotonically, so every point's cell lies in
        // [floor(lo·inv), floor(hi·inv)].
        let first = lo.map(|l| floor_i64(l * inv) >> 3);
        let last = hi.map(|h| floor_i64(h * inv) >> 3);
        let dims = [0, 1, 2].map(|a| last[a] - first[a] + 1);
        let count = dims.iter().try_fold(1i64, |acc, &d| acc.checked_mul(d))?;
        if count > (4 * points.len() as i64).max(4096) {
            return None;
        }
        Some(Bricks {
            origin: first.map(|b| b << 3),
            dims,
            blocks: vec![NONE; count as usize],
            slots: Vec::new(),
            budget: 16 * points.len() + 4096,
        })
    }
}

impl Slots for Bricks {
    const CHEAP: bool = true;

    #[inline(always)] // per point: a call costs as much as the lookup
    fn slot(&mut self, cell: [i64; 3], fresh: u32) -> Option<u32> {
        // Written out: `[T; N]::map` is not always inlined, and this runs per point.
        let rel = [
            cell[0] - self.origin[0],
            cell[1] - self.origin[1],
            cell[2] - self.origin[2],
        ];
        let brick = ((rel[0] >> 3) * self.dims[1] + (rel[1] >> 3)) * self.dims[2] + (rel[2] >> 3);
        let block = self.blocks.get_mut(usize::try_from(brick).ok()?)?;
        if *block == NONE {
            if self.slots.len() >= self.budget {
                return None; // a sparse cloud: hashing it takes less memory
            }
            *block = (self.slots.len() / 512) as u32;
            self.slots.resize(self.slots.len() + 512, NONE);
        }
        let within = ((rel[0] & 7) << 6 | (rel[1] & 7) << 3 | (rel[2] & 7)) as usize;
        let slot = &mut self.slots[*block as usize * 512 + within];
        if *slot == NONE {
            *slot = fresh;
        }
        Some(*slot)
    }
}

/// Sums per voxel, in order of each voxel's first point, then means; `None` as soon
/// as a cell has no slot.
fn accumulate<I: Slots>(
    points: &[[f64; 3]],
    values: Option<(&[f64], usize)>,
    inv: f64,
    mut index: I,
) -> Option<(Vec<[f64; 3]>, Vec<f64>)> {
    // Per voxel the sums of x, y and z and the number of points.
    let mut voxels: Vec<[f64; 4]> = Vec::new();
    // Every point's voxel, kept only when values are averaged too.
    let mut slots: Vec<u32> = Vec::with_capacity(if values.is_some() { points.len() } else { 0 });
    // The current voxel as [lo, lo + 1) in cell units per axis (NaN: none yet).
    // Points of a depth image come row by row: the previous point's voxel is often
    // this one's too (44 % of a frame's points), and comparisons are cheaper than a
    // key and a hash, though not than a mispredicted branch and two array reads.
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
        if I::CHEAP || !inside {
            // Written out, as in `Bricks::slot`.
            let cell = [floor_i64(v[0]), floor_i64(v[1]), floor_i64(v[2])];
            slot = index.slot(cell, voxels.len() as u32)? as usize;
            if slot == voxels.len() {
                voxels.push([0.0; 4]);
            }
            if !I::CHEAP {
                lo = [cell[0] as f64, cell[1] as f64, cell[2] as f64];
                hi = [lo[0] + 1.0, lo[1] + 1.0, lo[2] + 1.0];
            }
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

#[cfg(test)]
mod tests {
    use super::*;
    use crate::synthetic::Rng;
    use std::collections::BTreeMap;

    /// Centroids and mean values in order of each voxel's first point, by a map from
    /// cells to the points' indices.
    fn reference(points: &[[f64; 3]], size: f64, values: &[f64]) -> (Vec<[f64; 3]>, Vec<f64>) {
        let mut members: BTreeMap<[i64; 3], Vec<usize>> = BTreeMap::new();
        for (i, p) in points.iter().enumerate() {
            members
                .entry(p.map(|c| (c / size).floor() as i64))
                .or_default()
                .push(i);
        }
        let mut groups: Vec<&Vec<usize>> = members.values().collect();
        groups.sort_by_key(|g| g[0]);
        let centroids = groups
            .iter()
            .map(|g| {
                [0, 1, 2].map(|a| g.iter().map(|&i| points[i][a]).sum::<f64>() / g.len() as f64)
            })
            .collect();
        let means = groups
            .iter()
            .flat_map(|g| {
                [0, 1].map(|j| g.iter().map(|&i| values[2 * i + j]).sum::<f64>() / g.len() as f64)
            })
            .collect();
        (centroids, means)
    }

    #[test]
    fn every_index_gives_the_reference_voxels() {
        let mut rng = Rng::new(31);
        // A compact cloud (13³ bricks), one 400 m wide (packed keys), one 2·10^7 m wide
        // (general keys), each with runs of neighbouring points as in a depth image.
        for (extent, size) in [(1.0, 0.02), (200.0, 0.05), (1e7, 0.05)] {
            let mut points = Vec::new();
            while points.len() < 5000 {
                let start = [0, 1, 2].map(|_| rng.uniform(-extent, extent));
                for k in 0..(1 + (rng.unit() * 8.0) as usize) {
                    points.push(start.map(|c| c + 0.004 * k as f64 + 0.01 * rng.normal()));
                }
            }
            let values: Vec<f64> = (0..2 * points.len())
                .map(|_| rng.uniform(0.0, 255.0))
                .collect();
            let (centroids, means) = voxel_downsample(&points, size, Some((&values, 2))).unwrap();
            let (want, want_means) = reference(&points, size, &values);
            check(&centroids, &means, &want, &want_means, extent);
        }
        // Sparse in a small box: the bricks would take 2 KB a point and give way to hashing.
        let points: Vec<[f64; 3]> = (0..20_000)
            .map(|_| [rng.unit(), rng.unit(), rng.unit()])
            .collect();
        let values: Vec<f64> = (0..2 * points.len()).map(|_| rng.unit()).collect();
        let (centroids, means) = voxel_downsample(&points, 0.004, Some((&values, 2))).unwrap();
        let (want, want_means) = reference(&points, 0.004, &values);
        check(&centroids, &means, &want, &want_means, 1.0);
        // Cells too small to tell the points apart (indices past 2^50) are an error,
        // not one saturated voxel.
        let huge = [[1e19, 0.0, 0.0], [2e19, 0.0, 0.0], [-3e19, 1.0, 0.0]];
        assert!(voxel_downsample(&huge, 1.0, None).is_err());
        assert!(voxel_downsample(&[[1.0, 0.0, 0.0], [0.5, 0.0, 0.0]], 1e-300, None).is_err());
    }

    fn check(
        centroids: &[[f64; 3]],
        means: &[f64],
        want: &[[f64; 3]],
        want_means: &[f64],
        extent: f64,
    ) {
        assert_eq!(centroids.len(), want.len(), "extent {extent}");
        for (c, w) in centroids.iter().zip(want) {
            for a in 0..3 {
                assert!(
                    (c[a] - w[a]).abs() <= 1e-9 * (1.0 + w[a].abs()),
                    "extent {extent}: {c:?} vs {w:?}"
                );
            }
        }
        for (m, w) in means.iter().zip(want_means) {
            assert!((m - w).abs() < 1e-9, "extent {extent}");
        }
    }

    /// Codes against the formula written out (floor of p / resolution, offset by 2^20,
    /// 21 bits per axis), including the last cells on either side of the range.
    #[test]
    fn voxel_codes_pack_21_bits_per_axis() {
        let mut rng = Rng::new(11);
        for resolution in [0.05, 0.013, 1.0, 1e-4] {
            let reach = 1_048_575.0 * resolution;
            let mut points: Vec<[f64; 3]> = (0..500)
                .map(|_| std::array::from_fn(|_| rng.uniform(-reach, reach)))
                .collect();
            points.push([-reach, reach, 0.0]);
            let codes = voxel_codes(&points, resolution).unwrap();
            for (p, &code) in points.iter().zip(&codes) {
                let k = p.map(|c| (c / resolution).floor() as i64 + (1 << 20));
                assert_eq!(code, k[0] << 42 | k[1] << 21 | k[2], "{p:?}");
                assert!(k.iter().all(|&v| (1..1 << 21).contains(&v)));
            }
        }
        assert_eq!(voxel_codes(&[], 0.1).unwrap(), Vec::<i64>::new());
        for bad in [
            [f64::NAN, 0.0, 0.0],
            [0.0, f64::INFINITY, 0.0],
            [0.0, 0.0, 1048576.0 * 0.05],
            [-1048576.0 * 0.05 - 1e-9, 0.0, 0.0],
        ] {
            let err = voxel_codes(&[[0.0; 3], bad], 0.05).unwrap_err().to_string();
            assert!(err.contains("within 2^20 cells of size 0.05"), "{err}");
        }
        for res in [0.0, -1.0, f64::NAN, f64::INFINITY] {
            let err = voxel_codes(&[[0.0; 3]], res).unwrap_err().to_string();
            assert!(err.contains("resolution must be finite and > 0"), "{err}");
        }
        assert_eq!(
            pack_cell([-(1 << 20), 0, (1 << 20) - 1]),
            Some((1 << 20) << 21 | ((1 << 21) - 1))
        );
        assert_eq!(pack_cell([1 << 20, 0, 0]), None);
        assert_eq!(pack_cell([0, -(1 << 20) - 1, 0]), None);
    }
}
