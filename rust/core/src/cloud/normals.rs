//! Surface normals by principal component analysis of each point's neighbourhood:
//! the direction of least spread of the point and its k nearest neighbours, turned
//! to face a viewpoint (the sensor).

use super::kdtree::KdTree;
use crate::error::{Error, Result};
use crate::na::{Matrix3, Vector3};
use crate::threads;

/// Unit normals and surface variations, one per point.
pub type Normals = (Vec<[f64; 3]>, Vec<f64>);

/// Unit normals (one per point) and the surface variation λ_min / (λ0 + λ1 + λ2)
/// (0 on a perfect plane, 1/3 for isotropic scatter).
///
/// Cost: O(N log N) for the index plus, per point, the k-neighbour query (O(k log k)
/// beyond the points it visits) and O(k) for the covariance; k near N makes the
/// whole O(N²): see [`estimate_normals_interruptible`] to stop such a call.
pub fn estimate_normals(points: &[[f64; 3]], k: usize, viewpoint: [f64; 3]) -> Result<Normals> {
    let result = estimate_normals_interruptible(points, k, viewpoint, &mut || false)?;
    // Never asked to stop, so always computed.
    result.ok_or_else(|| Error::InvalidArgument("normal estimation was interrupted".into()))
}

/// [`estimate_normals`], asking `interrupt` on the calling thread every few
/// milliseconds of work (the points are processed in rounds sized by k); `Ok(None)`
/// when it asked to stop.
pub fn estimate_normals_interruptible(
    points: &[[f64; 3]],
    k: usize,
    viewpoint: [f64; 3],
    interrupt: &mut threads::Interrupt<'_>,
) -> Result<Option<Normals>> {
    if k < 2 {
        return Err(Error::InvalidArgument(format!(
            "normals need k >= 2 neighbours, got {k}"
        )));
    }
    if points.len() <= k {
        return Err(Error::InvalidArgument(format!(
            "normal estimation needs more points than k = {k} neighbours, got {}",
            points.len()
        )));
    }
    crate::geometry::check_finite(points, "point")?;
    if !viewpoint.iter().all(|c| c.is_finite()) {
        return Err(Error::InvalidArgument(format!(
            "viewpoint {viewpoint:?} is not finite"
        )));
    }
    let tree = KdTree::new(points);
    // Queries in Morton order hit the tree's memory coherently; results go back in place.
    let order = crate::geometry::morton_order(points);
    // A chunk's work grows with k: fewer points per chunk keep a round of chunks
    // to milliseconds, so an interrupt is seen soon whatever k is.
    let chunk = ((1usize << 17) / k).clamp(1, 4096);
    let chunks: Vec<&[u32]> = order.chunks(chunk).collect();
    let mapped = threads::map_parts_interruptible(
        &chunks,
        |chunk| {
            let mut nn = Vec::with_capacity(k);
            chunk
                .iter()
                .map(|&i| {
                    let i = i as usize;
                    tree.knn(points[i], k, Some(i as u32), &mut nn);
                    let neighbourhood = std::iter::once(points[i])
                        .chain(nn.iter().map(|&(_, j)| points[j as usize]));
                    (
                        i,
                        normal_of(neighbourhood, nn.len() + 1, points[i], viewpoint),
                    )
                })
                .collect::<Vec<_>>()
        },
        interrupt,
    );
    let Some(parts) = mapped else {
        return Ok(None);
    };
    let mut normals = vec![[0.0; 3]; points.len()];
    let mut variation = vec![0.0; points.len()];
    for (i, (n, v)) in parts.into_iter().flatten() {
        normals[i] = n;
        variation[i] = v;
    }
    Ok(Some((normals, variation)))
}

fn normal_of(
    pts: impl Iterator<Item = [f64; 3]> + Clone,
    n: usize,
    at: [f64; 3],
    viewpoint: [f64; 3],
) -> ([f64; 3], f64) {
    let mean = pts
        .clone()
        .fold(Vector3::zeros(), |acc, p| acc + Vector3::from(p))
        / n as f64;
    let cov = pts.fold(Matrix3::zeros(), |acc, p| {
        let d = Vector3::from(p) - mean;
        acc + d * d.transpose()
    }) / n as f64;
    let (values, mut normal) = crate::eigen3::symmetric_eigen3(&cov);
    if normal.dot(&(Vector3::from(viewpoint) - Vector3::from(at))) < 0.0 {
        normal = -normal;
    }
    let total: f64 = values.iter().sum();
    let variation = if total > 0.0 {
        values[0].max(0.0) / total
    } else {
        0.0
    };
    ([normal.x, normal.y, normal.z], variation)
}
