//! Euclidean clustering on a grid: points in the same or touching cells (26
//! neighbours) belong to one cluster. On voxel centres at the map's resolution this is
//! the connected components of the occupied voxels, which the reflex layer tracks as
//! obstacles (Paper II §C.6).

use rustc_hash::FxHashMap;

use crate::error::{Error, Result};
use crate::floor::floor_i64;

/// Cluster label per point (0, 1, ... in order of each cluster's first point).
pub fn cluster_points(points: &[[f64; 3]], cell: f64) -> Result<Vec<u32>> {
    if !(cell.is_finite() && cell > 0.0) {
        return Err(Error::InvalidArgument(format!(
            "cell size must be finite and > 0, got {cell}"
        )));
    }
    crate::geometry::check_finite(points, "point")?;
    crate::geometry::check_cell_range(points, cell, "cell size")?;
    // Fx hashing: the reflex layer clusters every frame, and SipHash was most of it.
    let mut cells: FxHashMap<[i64; 3], u32> =
        FxHashMap::with_capacity_and_hasher(points.len(), Default::default());
    let mut parent: Vec<u32> = Vec::with_capacity(points.len());
    let mut of_point = Vec::with_capacity(points.len());
    for p in points {
        let key = p.map(|v| floor_i64(v / cell));
        let id = *cells.entry(key).or_insert_with(|| {
            parent.push(parent.len() as u32);
            (parent.len() - 1) as u32
        });
        of_point.push(id);
    }
    // Union each occupied cell with its occupied neighbours (half of the 26 offsets
    // suffice: the other half is the same pairs seen from the other side).
    let offsets: Vec<[i64; 3]> = (-1..=1)
        .flat_map(|x| (-1..=1).flat_map(move |y| (-1..=1).map(move |z| [x, y, z])))
        .filter(|o| *o > [0, 0, 0])
        .collect();
    for (key, &id) in &cells {
        for o in &offsets {
            let n = [key[0] + o[0], key[1] + o[1], key[2] + o[2]];
            if let Some(&other) = cells.get(&n) {
                union(&mut parent, id, other);
            }
        }
    }
    let mut label_of_root: FxHashMap<u32, u32> = FxHashMap::default();
    Ok(of_point
        .iter()
        .map(|&id| {
            let root = find(&mut parent, id);
            let next = label_of_root.len() as u32;
            *label_of_root.entry(root).or_insert(next)
        })
        .collect())
}

fn find(parent: &mut [u32], mut x: u32) -> u32 {
    while parent[x as usize] != x {
        let up = parent[parent[x as usize] as usize];
        parent[x as usize] = up; // path halving
        x = up;
    }
    x
}

fn union(parent: &mut [u32], a: u32, b: u32) {
    let (ra, rb) = (find(parent, a), find(parent, b));
    if ra != rb {
        parent[ra.max(rb) as usize] = ra.min(rb);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn touching_cells_join_and_gaps_split() {
        let r = 0.05;
        let c = |i: i64, j: i64, k: i64| {
            [
                (i as f64 + 0.5) * r,
                (j as f64 + 0.5) * r,
                (k as f64 + 0.5) * r,
            ]
        };
        // A diagonal chain (corner-touching), then a cell two steps away.
        let pts = vec![c(0, 0, 0), c(1, 1, 1), c(2, 2, 1), c(4, 2, 1), c(0, 0, 0)];
        assert_eq!(cluster_points(&pts, r).unwrap(), vec![0, 0, 0, 1, 0]);
    }

    #[test]
    fn matches_brute_force_components() {
        // Random voxels on a small grid; compare with a flood fill over the pairs.
        let mut state = 12345u64;
        let mut rnd = || {
            state = state
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            (state >> 33) % 12
        };
        let r = 0.1;
        let pts: Vec<[f64; 3]> = (0..300)
            .map(|_| [rnd(), rnd(), rnd()].map(|v| (v as f64 + 0.5) * r))
            .collect();
        let labels = cluster_points(&pts, r).unwrap();
        let n = pts.len();
        let near = |a: &[f64; 3], b: &[f64; 3]| (0..3).all(|i| (a[i] - b[i]).abs() < 1.5 * r);
        let mut comp = vec![usize::MAX; n];
        let mut next = 0;
        for s in 0..n {
            if comp[s] != usize::MAX {
                continue;
            }
            let mut stack = vec![s];
            comp[s] = next;
            while let Some(i) = stack.pop() {
                for j in 0..n {
                    if comp[j] == usize::MAX && near(&pts[i], &pts[j]) {
                        comp[j] = next;
                        stack.push(j);
                    }
                }
            }
            next += 1;
        }
        for i in 0..n {
            for j in 0..n {
                assert_eq!(labels[i] == labels[j], comp[i] == comp[j]);
            }
        }
    }

    #[test]
    fn bad_input() {
        assert!(cluster_points(&[[0.0; 3]], 0.0).is_err());
        assert!(cluster_points(&[[f64::NAN, 0.0, 0.0]], 0.1).is_err());
        assert!(cluster_points(&[], 0.1).unwrap().is_empty());
        // Cells too small (or points too far) to tell points apart.
        assert!(cluster_points(&[[1.0, 0.0, 0.0], [0.5, 0.0, 0.0]], 1e-300).is_err());
        assert!(cluster_points(&[[1e300, 0.0, 0.0], [-1e300, 0.0, 0.0]], 1.0).is_err());
    }
}
